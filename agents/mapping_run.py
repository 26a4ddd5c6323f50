"""Drive one robot over a world (or replay a log) and feed its scans to the particle filter.

This is the loop behind ``wiremap map``, ``wiremap bench accuracy/speed`` and the fleet's robot
agent (:func:`robot_steps`). It is split in two so that the same scans can be fed to several
filters (the accuracy benchmark runs the filter and the single-hypothesis baseline on identical
scans):

* **scan sources** yield :class:`ScanInput` (time, odometry increment, robot-frame scan and the
  true pose when there is one): :func:`simulate` (a world, its coverage route, the motion model
  and the corner sensor or a simulated lidar -- clean, or realistic with noise, dropouts, glass,
  clutter and people, :mod:`agents.sim.real_lidar` -- plus split-and-merge) and :func:`carmen_inputs`
  (a CARMEN log's ``FLASER`` lines through split-and-merge);
* :func:`run_filter` feeds them to a :class:`~mapping.filter.WireframeFilter` and yields a
  :class:`RunStep` per scan: step index, time, true pose, estimated pose, scan, the filter.

Randomness: one integer seed is split (``numpy.random.SeedSequence.spawn``) into independent
generators for the route, the odometry noise, the sensor and the filter, so the scans of a seed
do not depend on the filter's settings.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapping.config import with_overrides
from mapping.filter import FilterConfig, StepInfo, WireframeFilter
from mapping.lidar_frontend import odometry_overrides
from mapping.se2 import Pose, increments
from mapping.wireframe import Wireframe

__all__ = [
    "SENSORS",
    "LogCalibration",
    "RunStep",
    "ScanInput",
    "SimOptions",
    "calibrate_log",
    "carmen_inputs",
    "default_merge_threshold",
    "filter_config_for",
    "for_scanner",
    "judged_sweep",
    "lidar_profile",
    "odometry_report",
    "robot_steps",
    "run_filter",
    "scan_fov",
    "simulate",
    "split_profile",
    "sweep_check",
    "world_defaults",
    "yaw_report",
]

#: The simulated sensors: the corner sensor (paper Sec. IV-A), the clean lidar (ray casting,
#: 1 cm noise) and the realistic lidar (:mod:`agents.sim.real_lidar`), both through split-and-merge.
SENSORS = ("corners", "lidar", "lidar-real")


@dataclass(frozen=True)
class ScanInput:
    """One scan to feed the filter.

    Attributes
    ----------
    t : float
        Time of the scan (simulation seconds, or the log's timestamp).
    odometry : Pose
        Motion since the previous scan in the previous robot frame (identity for the first).
    scan : Wireframe
        The corner scan in the robot frame.
    true_pose : Pose or None
        The true pose in the world frame, when known (simulation).
    points : (n, 2) float64 or None
        The scan's raw points (robot frame, bearing order; a real lidar's), for the filter's
        point match (:attr:`mapping.filter.FilterConfig.point_match`).
    warp : ((m, 3), (m, 3)) float64 or None
        The online SLAM's nodes before and after a loop reshaped its graph, before this scan:
        the map is carried along (:func:`feed`; ``frontend.follow_graph``).
    """

    t: float
    odometry: Pose
    scan: Wireframe
    true_pose: Pose | None = None
    points: NDArray[np.float64] | None = None
    warp: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None


@dataclass(frozen=True)
class SimOptions:
    """How to simulate a robot.

    Attributes
    ----------
    sensor : str
        ``"corners"`` (the simulated corner sensor, paper Sec. IV-A), ``"lidar"`` (ray-cast
        ranges turned into corners by split-and-merge, :mod:`mapping.extract`) or
        ``"lidar-real"`` (the same lidar with what real scans have: range noise growing with
        range, dropouts, max-range bursts, glass, clutter and walking people,
        :mod:`agents.sim.real_lidar`).
    max_range : float
        Sensing range (metres) of either sensor; the filter predicts scans with the same range.
    speed, dt : float
        Driving speed (m/s) and scan period (s): one scan every ``speed * dt`` metres (0.25 m).
    steps : int, optional
        Stop after this many scans.
    duration : float, optional
        Stop after this many simulated seconds.
    corner_sigma, corner_p_fp, corner_p_fn : float
        Corner sensor noise (see :class:`agents.sim.sensor.CornerSensorConfig`).
    lidar_beams, lidar_sigma : int, float
        The simulated lidar: a full turn of ``lidar_beams`` beams with ``lidar_sigma`` range
        noise (a 360-degree scanner, so both sensors see the same field of view). The realistic
        lidar has the same beams; ``real.noise`` replaces ``lidar_sigma``.
    real : agents.sim.real_lidar.RealLidarConfig, optional
        The realistic lidar's noise and scene (its defaults without).
    scene_seed : int, optional
        Seed of the realistic lidar's scene (glass, clutter, people;
        :func:`agents.sim.real_lidar.build_scene`); default the run's seed. A fleet's robots
        share one, as they share the building.
    extract : mapping.extract.ExtractConfig, optional
        Split-and-merge settings for either lidar (its defaults without).
    """

    sensor: str = "corners"
    max_range: float = 8.0
    speed: float = 0.5
    dt: float = 0.5
    steps: int | None = None
    duration: float | None = None
    corner_sigma: float = 0.02
    corner_p_fp: float = 0.02
    corner_p_fn: float = 0.02
    lidar_beams: int = 720
    lidar_sigma: float = 0.01
    extra: dict[str, Any] = field(default_factory=dict)
    real: Any = None
    scene_seed: int | None = None
    extract: Any = None

    def __post_init__(self) -> None:
        if self.sensor not in SENSORS:
            raise ValueError(f"sensor must be one of {', '.join(SENSORS)}, got {self.sensor!r}")
        if not (math.isfinite(self.max_range) and self.max_range > 0):
            raise ValueError(f"max_range must be a positive number of metres, got {self.max_range}")
        if self.steps is not None and self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if self.duration is not None and not self.duration > 0:
            raise ValueError(f"duration must be > 0, got {self.duration}")


@dataclass(frozen=True)
class RunStep:
    """The state after one filter step.

    Attributes
    ----------
    index : int
        0-based index of the scan.
    total : int or None
        Number of scans in the run when known.
    t : float
        Time of the scan.
    true_pose : Pose or None
        True pose (world frame) when known.
    pose : Pose
        The filter's pose estimate (map frame).
    scan : Wireframe
        The scan (robot frame).
    filter : WireframeFilter
        The filter, after the step.
    info : StepInfo
        What the step did.
    step_s : float
        Wall-clock seconds of :meth:`WireframeFilter.step` alone.
    """

    index: int
    total: int | None
    t: float
    true_pose: Pose | None
    pose: Pose
    scan: Wireframe
    filter: WireframeFilter
    info: StepInfo
    step_s: float


def default_merge_threshold(world: Any) -> float:
    """The paper's merge thresholds: 0.4 m for a large world (a side over 100 m), else 0.2 m."""
    w, h = world.size
    return 0.4 if max(w, h) > 100.0 else 0.2


def world_defaults(world: Any) -> tuple[int, float]:
    """The paper's ``(particles, merge threshold)`` for ``world``: 6 and 0.4 m for a large world
    (a side over 100 m), else 10 and 0.2 m (``wiremap bench accuracy``, ``wiremap config show``)."""
    thr = default_merge_threshold(world)
    return (6 if max(world.size) > 100.0 else 10), thr


def filter_config_for(
    particles: int,
    merge_threshold: float,
    max_range: float,
    fov: float = 2.0 * math.pi,
    overrides: Mapping[str, Any] | None = None,
) -> FilterConfig:
    """The filter configuration used by the commands: these settings, then ``overrides``
    (``{dotted key: value or its text}``, :func:`mapping.config.with_overrides`; raises its
    ``ConfigError``). One particle gives the baseline (single hypothesis, no mutation):
    ``mutate`` follows the final particle count unless ``overrides`` sets it."""
    cfg = FilterConfig(
        particles=particles,
        merge_threshold=merge_threshold,
        max_range=max_range,
        fov=fov,
        mutate=particles > 1,
    )
    if not overrides:
        return cfg
    cfg = with_overrides(cfg, overrides)
    if "mutate" not in overrides and cfg.mutate != (cfg.particles > 1):
        cfg = replace(cfg, mutate=cfg.particles > 1)
    return cfg


#: The real-lidar profile (:func:`lidar_profile`); each value's evidence is in docs/experiments.md,
#: "Real lidar", with the command that measures it.
LIDAR_PROFILE: dict[str, Any] = {
    # The CARMEN logs' odometry errs by ~5 % of the distance and ~2 degrees per metre; the
    # filter's defaults (1.5 x the simulator's: 3 %, 0.17 degrees/m) made the ICP's prior ten
    # times too tight in heading. 1.4 x the logs' noise: median ATE 1.59 -> 0.42 m.
    **odometry_overrides(),
    # Real scanners' beams are 1 degree apart (17 cm at 10 m): a run's break grows with range
    # (mapping.extract.ExtractConfig.jump_beams). Median ATE 0.338 -> 0.313 m, precision
    # 0.743 -> 0.841, coverage 0.479 -> 0.602.
    "extract.jump_beams": 3.0,
    # The laser's yaw against the odometry's direction of travel, applied when pinned down
    # (mapping.lidar_frontend.laser_yaw): fhw +0.28 degrees (4.5 standard errors), the other
    # logs none. fhw's ATE 0.323 -> 0.26 m (docs/experiments.md, "The laser's yaw").
    "frontend.yaw_calibration": True,
    "frontend.scale_calibration": True,
}

#: The ``lidar-slam`` profile: the real-lidar profile with lidar SLAM under the filter
#: (mapping.lidar_slam: every scan point matched against the recent and nearby old scans,
#: loops closed against old ones, the pose graph optimised over the whole log), the filter then
#: mapping at the SLAM's poses. Its own pose corrections (the corner ICP, the compass, its loop
#: closer, the refinement) only pull a held pose off, so they are off. Against ``lidar`` on the
#: seven logs (seed 1): worst ATE 6.54 -> 1.26 m, relative error 0.059 -> 0.027 m, but median ATE
#: 0.313 -> 0.323 m and precision 0.841 -> 0.794 (docs/experiments.md, "Lidar SLAM under the
#: filter" and "Offline refinement").
LIDAR_SLAM_PROFILE: dict[str, Any] = {
    **LIDAR_PROFILE,
    "slam.enabled": True,
    # The SLAM's heading prior per metre widened to 3x the log's own wheels' measured noise
    # (mapping.lidar_frontend.odometry_noise; no truth used): orebro's 1.8 degrees per metre
    # against 0.4-1.0 on the others. With the per-radian prior at 0.02: bench slam median /
    # worst ATE 0.164 / 0.484 -> 0.157 / 0.439 m (docs/experiments.md, "The SLAM's heading prior
    # fitted to the log's own wheels").
    "slam.odo_calibration": True,
    # A scan maps only once the robot has driven 0.5 m or turned 0.25 rad since the last one
    # that did (GMapping's linearUpdate / angularUpdate, at half its 1 m / 0.5 rad): scans taken
    # standing still add nothing. fhw's precision 0.847 -> 0.870, the others within 0.003
    # (docs/experiments.md, "Map updates gated by distance and turn").
    "gating.update_distance": 0.5,
    "gating.update_angle": 0.25,
    "use_icp": False,
    "compass.enabled": False,
    "loops.enabled": False,
    "refine.enabled": False,
}

#: ``lidar-slam`` as a robot mapping while it drives runs it: each scan mapped at the pose the
#: SLAM gave it when it came (``slam.online``; no offline smoothing), the laser's yaw and the
#: wheels' noise measured on the first 100 scans only (``frontend.calibration_scans``), and a loop
#: that moves the estimate less than 2 cm and 0.2 degree *settled* (``slam.loop_settled_xy``,
#: ``loop_settled_theta``: its edge kept, the graph not optimised for it), and a scan taken where
#: the graph holds two visits already, within 0.5 m and 20 degrees, and located on the old walls
#: *redundant*, no node of the graph (``slam.revisit_xy``, ``revisit_theta``, ``revisit_visits``),
#: so that a robot driving a building it has mapped keeps its time per scan and its memory
#: (``wiremap bench live``; docs/experiments.md, "Session 27"); and when a loop reshapes the
#: graph, the map built so far moves with it (``frontend.follow_graph``: a live robot's map after
#: the first pass of the seven logs, median precision 0.595 -> 0.906); and the graph is refined
#: while the robot drives, 8 nodes a scan matched again against the other visits of their places
#: (``slam.refine_online_nodes``: after ten passes of the seven logs, median precision 0.789 ->
#: 0.900, the tenth pass's ATE 0.270 -> 0.126 m; docs/experiments.md, "Session 28").
LIDAR_SLAM_ONLINE_PROFILE: dict[str, Any] = {
    **LIDAR_SLAM_PROFILE,
    "slam.online": True,
    "frontend.calibration_scans": 100,
    "slam.loop_settled_xy": 0.02,
    "slam.loop_settled_theta": math.radians(0.2),
    "slam.revisit_xy": 0.5,
    "slam.revisit_theta": math.radians(20.0),
    "slam.revisit_visits": 2,
    "frontend.follow_graph": True,
    "slam.refine_online_nodes": 8,
}

#: The real-lidar profiles by name (``--profile`` of ``wiremap bench lidar``, ``--lidar-profile``
#: of ``wiremap map``).
LIDAR_PROFILES: dict[str, dict[str, Any]] = {"lidar": LIDAR_PROFILE, "lidar-slam": LIDAR_SLAM_PROFILE,
                                              "lidar-slam-online": LIDAR_SLAM_ONLINE_PROFILE}


def lidar_profile(name: str = "lidar") -> dict[str, Any]:
    """The settings for a real lidar (``wiremap bench lidar``, ``wiremap map --carmen``), as
    dotted overrides: ``extract.*`` for split-and-merge (:class:`mapping.extract.ExtractConfig`),
    ``frontend.*`` for the raw points (:class:`mapping.lidar_frontend.FrontendConfig`), the
    rest for :class:`mapping.filter.FilterConfig` (:func:`split_profile`). The simulator's
    defaults do not use it. ``name``: a key of :data:`LIDAR_PROFILES`."""
    return dict(LIDAR_PROFILES[name])


def split_profile(overrides: dict[str, Any]) -> tuple[dict[str, Any], Any, Any]:
    """``(filter overrides, ExtractConfig, FrontendConfig)`` from dotted overrides as
    :func:`lidar_profile` gives them.

    Raises
    ------
    mapping.config.ConfigError
        A key names no setting, or a value is out of range.
    """
    from mapping.config import with_overrides
    from mapping.extract import ExtractConfig
    from mapping.lidar_frontend import FrontendConfig

    groups: dict[str, dict[str, Any]] = {"extract": {}, "frontend": {}, "filter": {}}
    for key, value in overrides.items():
        head, dot, rest = key.partition(".")
        if dot and head in ("extract", "frontend"):
            groups[head][rest] = value
        elif dot and head == "slam":
            groups["frontend"][key] = value
        else:
            groups["filter"][key] = value
    return (
        groups["filter"],
        with_overrides(ExtractConfig(), groups["extract"]),
        with_overrides(FrontendConfig(), groups["frontend"]),
    )


def seeds_for(seed: int) -> dict[str, np.random.Generator]:
    """Independent generators for the route, the odometry, the sensor and the filter."""
    names = ("route", "drive", "sensor", "filter")
    kids = np.random.SeedSequence(int(seed)).spawn(len(names))
    return {n: np.random.default_rng(k) for n, k in zip(names, kids)}


def simulate(
    world: Any,
    options: SimOptions,
    seed: int,
    *,
    route: NDArray[np.float64] | None = None,
    start: tuple[float, float] | None = None,
) -> Iterator[ScanInput]:
    """Scans of a robot driving a coverage route through ``world``.

    Parameters
    ----------
    world : agents.sim.world.World
    options : SimOptions
    seed : int
    route : (k, 2) array, optional
        Drive this route instead of planning one (:func:`agents.sim.route.plan_route`).
    start : (x, y), optional
        Start of the planned route.

    Yields
    ------
    ScanInput
    """
    from agents.sim.motion import drive
    from agents.sim.route import plan_route

    rngs = seeds_for(seed)
    if route is None:
        route = plan_route(world, rngs["route"], start=start, sensor_range=options.max_range)
    steps = drive(route, speed=options.speed, dt=options.dt, rng=rngs["drive"])
    if options.steps is not None:
        steps = steps[: options.steps]
    if options.duration is not None:
        steps = [s for s in steps if s.t <= options.duration + 1e-9]
    scan_fn = _scanner(world, options, route, seed if options.scene_seed is None else options.scene_seed)
    srng = rngs["sensor"]
    for s in steps:
        scan, points = scan_fn(s.true_pose, srng, s.t)
        yield ScanInput(s.t, s.odometry, scan, s.true_pose, points)


def sim_step_counts(
    world: Any, options: SimOptions, seed: int, route: NDArray[np.float64] | None = None
) -> tuple[int, int]:
    """``(scans simulate yields, scans of the whole route)``: the first is cut by
    ``options.steps`` and ``options.duration``, the second is not (one route plan for both)."""
    from agents.sim.motion import drive
    from agents.sim.route import plan_route

    rngs = seeds_for(seed)
    if route is None:
        route = plan_route(world, rngs["route"], sensor_range=options.max_range)
    steps = drive(route, speed=options.speed, dt=options.dt, rng=rngs["drive"])
    n = whole = len(steps)
    if options.steps is not None:
        n = min(n, options.steps)
    if options.duration is not None:
        n = sum(1 for s in steps[:n] if s.t <= options.duration + 1e-9)
    return n, whole


def _scanner(world: Any, options: SimOptions, route: NDArray[np.float64], scene_seed: int) -> Any:
    """``scan(true pose, sensor rng, time) -> (corner scan, raw points or None)`` of
    ``options.sensor``. The realistic lidar gives its raw points
    (:func:`mapping.lidar_frontend.scan_points`), as a real lidar's front end does
    (:func:`carmen_inputs`); the clean sensors give none, as they always have."""
    if options.sensor == "corners":
        from agents.sim.sensor import CornerSensor, CornerSensorConfig

        sensor = CornerSensor(
            world.truth,
            CornerSensorConfig(
                max_range=options.max_range,
                sigma=options.corner_sigma,
                p_fp=options.corner_p_fp,
                p_fn=options.corner_p_fn,
            ),
        )

        def corner_scan(pose: Pose, rng: np.random.Generator, t: float) -> tuple[Wireframe, None]:
            return sensor.scan(pose, rng), None

        return corner_scan
    from agents.sim.lidar import LidarConfig, raycast
    from mapping.extract import extract_corners

    lcfg = LidarConfig(beams=options.lidar_beams, fov=2.0 * math.pi, max_range=options.max_range,
                       sigma=options.lidar_sigma)
    angles = lcfg.angles()
    ecfg = options.extract

    def corners(ranges: NDArray[np.float64]) -> Wireframe:
        if ecfg is None:
            return extract_corners(ranges, angles, lcfg.max_range)
        return extract_corners(ranges, angles, lcfg.max_range, ecfg)

    if options.sensor == "lidar-real":
        from agents.sim.real_lidar import RealLidarConfig, build_scene, realistic_scan
        from mapping.lidar_frontend import FrontendConfig, scan_points

        real = options.real if options.real is not None else RealLidarConfig()
        scene = build_scene(world, real.scene, scene_seed).clear_of(route, real.scene.route_clearance)
        fcfg = FrontendConfig()

        def real_scan(pose: Pose, rng: np.random.Generator, t: float) -> tuple[Wireframe, Any]:
            ranges = realistic_scan(scene, pose, t, lcfg, real.noise, rng)
            return corners(ranges), scan_points(ranges, angles, fcfg)

        return real_scan

    segments = world.truth.segments()

    def lidar_scan(pose: Pose, rng: np.random.Generator, t: float) -> tuple[Wireframe, None]:
        return corners(raycast(segments, pose, lcfg, rng)), None

    return lidar_scan


def carmen_points(scans: Sequence[Any], frontend: Any) -> list[NDArray[np.float64]]:
    """Each CARMEN scan's points to match (:func:`mapping.lidar_frontend.scan_points` under the
    front end's settings ``frontend``): every return short of the scanner's saturation value,
    up to the front end's range."""
    from mapping.lidar_frontend import scan_points

    return [scan_points(np.where(np.asarray(ls.ranges) >= float(ls.max_range), np.inf,
                                 np.asarray(ls.ranges, dtype=np.float64)),
                        np.asarray(ls.angles, dtype=np.float64), frontend) for ls in scans]


@dataclass(frozen=True)
class LogCalibration:
    """What :func:`calibrate_log` made of a log's scans: the ``points`` to match (turned by
    ``turn``, the laser's yaw taken off every bearing, radians), the yaw ``estimate``
    (:class:`mapping.lidar_frontend.YawEstimate`; None when none was made), the wheels'
    heading ``noise`` (:class:`mapping.lidar_frontend.OdometryNoise`; None unless the SLAM
    runs with ``odo_calibration``) and their distance ``scale`` (every wheel increment's
    translation is divided by it: :func:`scaled`) with its estimate (``scale_estimate``,
    :class:`mapping.lidar_frontend.ScaleEstimate`; None unless ``frontend.scale_calibration``)."""

    points: list[NDArray[np.float64]]
    turn: float
    estimate: Any
    noise: Any
    scale: float = 1.0
    scale_estimate: Any = None
    scanner_range: float = math.inf


def for_scanner(frontend: Any, scans: Sequence[Any]) -> Any:
    """``frontend`` with its SLAM given the scanner's own range (``slam.scanner_range``: the
    median of the scans' ``max_range``) when its settings do not give one (inf), which turns
    the SLAM's check on the side of a wall a point was seen from on for a short-range scanner
    (``slam.facing_range``, :class:`mapping.lidar_slam.SlamConfig`). The same scans give the
    same front end."""
    ranges = [float(s.max_range) for s in scans]
    r = float(np.median(ranges)) if ranges else math.inf
    if not 0.0 < r < math.inf or math.isfinite(frontend.slam.scanner_range):
        return frontend
    return replace(frontend, slam=replace(frontend.slam, scanner_range=r))


def calibrate_log(scans: Sequence[Any], frontend: Any, yaw: float | None = None) -> LogCalibration:
    """A real log's calibrations, each made once: the laser's yaw (``yaw`` radians when given,
    else ``frontend.laser_yaw`` degrees when known, else the front end's estimate,
    :func:`mapping.lidar_frontend.laser_yaw`, when ``frontend.yaw_calibration`` is on) and,
    for a SLAM with ``odo_calibration``, the wheels'
    heading noise (:func:`mapping.lidar_frontend.odometry_noise`) on the points the SLAM gets,
    and with ``frontend.scale_calibration`` the wheels' distance scale
    (:func:`mapping.lidar_frontend.wheel_scale`). All rest on the same scan pairs
    (:func:`mapping.lidar_frontend.calibration_pairs`); they are matched again after the yaw
    turned the points, with the SLAM's settings for the scanner's range (:func:`for_scanner`)."""
    from mapping.lidar_frontend import calibration_pairs, laser_yaw, odometry_noise, wheel_scale

    frontend = for_scanner(frontend, scans)
    raw = carmen_points(scans, frontend)
    odometry = wheel_increments(scans)
    n = frontend.calibration_scans or len(raw)  # what the calibrations may look at
    pairs = None
    estimate = None
    if yaw is None and not math.isnan(frontend.laser_yaw):  # known: not estimated
        yaw = math.radians(frontend.laser_yaw)
    if yaw is None:
        if frontend.yaw_calibration:
            pairs = calibration_pairs(raw[:n], odometry[:n], frontend)
            estimate = laser_yaw(raw[:n], odometry[:n], frontend, pairs)
        yaw = estimate.correction if estimate is not None else 0.0
    pts = raw
    if yaw:
        c, s = math.cos(yaw), math.sin(yaw)
        turn = np.array([[c, -s], [s, c]])  # row vectors times this: turned by -yaw
        pts = [p @ turn for p in raw]
        pairs = None  # matched before the turn: the turned points are matched again when needed
    noise = None
    if frontend.slam.enabled and frontend.slam.odo_calibration:
        pairs = pairs if pairs is not None else calibration_pairs(pts[:n], odometry[:n], frontend)
        noise = odometry_noise(pts[:n], odometry[:n], frontend, pairs)
    scale = None
    if frontend.scale_calibration:
        pairs = pairs if pairs is not None else calibration_pairs(pts[:n], odometry[:n], frontend)
        scale = wheel_scale(pairs, frontend)
    return LogCalibration(pts, float(yaw), estimate, noise, 1.0 if scale is None else scale.correction, scale,
                          frontend.slam.scanner_range)


def odometry_report(noise: Any, slam: Any) -> dict[str, Any]:
    """The SLAM's odometry calibration (``noise``, a :class:`LogCalibration`'s, and the SLAM's
    settings ``slam`` before it) as report keys: ``odometry_heading_noise_deg_per_m`` (the
    wheels' measured heading error per metre; None with fewer than two pairs),
    ``odometry_heading_correlation`` (that error's lag-1 autocorrelation from one scan pair to
    the next: a smooth drift near 1; None with fewer than three pairs),
    ``odometry_noise_pairs``, ``slam_odo_rot_per_m_deg`` (the heading prior per metre the SLAM
    runs with, degrees: :func:`mapping.lidar_frontend.calibrated_slam`, as the SLAM applies it)
    and ``slam_odo_prior_widened`` (whether the calibration changed it). Empty without one."""
    from mapping.lidar_frontend import calibrated_slam

    if noise is None:
        return {}
    prior = calibrated_slam(slam, noise).odo_rot_per_m
    measured = math.degrees(noise.rot_per_m) if math.isfinite(noise.rot_per_m) else None
    return {"odometry_heading_noise_deg_per_m": measured,
            "odometry_heading_correlation": noise.correlation if math.isfinite(noise.correlation) else None,
            "odometry_noise_pairs": noise.pairs,
            "slam_odo_rot_per_m_deg": math.degrees(prior),
            "slam_odo_prior_widened": prior != slam.odo_rot_per_m}


def yaw_report(cal: LogCalibration) -> dict[str, Any]:
    """A log's laser-yaw and wheel-scale calibrations as report keys: ``laser_yaw_deg`` (the turn
    taken off every bearing: estimated, given or 0), and with an estimate ``laser_yaw_estimate_deg``
    and ``laser_yaw_se_deg`` (None when too few pairs gave it one: ``report.json`` stays strict
    JSON); with a scale estimate ``wheel_scale`` (what every wheel increment was divided by: 1
    when not applied), ``wheel_scale_estimate`` and ``wheel_scale_se``; ``scanner_range_m``, the
    scanner's own range (:func:`for_scanner`)."""
    out: dict[str, Any] = {"laser_yaw_deg": math.degrees(cal.turn)}
    if math.isfinite(cal.scanner_range):
        out["scanner_range_m"] = cal.scanner_range
    est = cal.estimate
    if est is not None:
        out["laser_yaw_estimate_deg"] = math.degrees(est.yaw)
        out["laser_yaw_se_deg"] = math.degrees(est.se) if math.isfinite(est.se) else None
    sc = cal.scale_estimate
    if sc is not None:
        out["wheel_scale"] = cal.scale
        out["wheel_scale_estimate"] = sc.scale
        out["wheel_scale_se"] = sc.se if math.isfinite(sc.se) else None
    return out


def wheel_increments(scans: Sequence[Any]) -> list[Pose]:
    """The wheel odometry's motion into each CARMEN scan from the previous one (the identity for
    the first)."""
    return increments([s.odom for s in scans])


def scaled(increment: Pose, scale: float) -> Pose:
    """A wheel increment with its translation divided by the wheels' distance ``scale``
    (:attr:`LogCalibration.scale`)."""
    return increment if scale == 1.0 else Pose(increment.x / scale, increment.y / scale, increment.theta)


def motion_filtered(
    scans: Sequence[Any], truth: Sequence[Pose] | None, frontend: Any, check: SweepCheck | None = None
) -> tuple[list[Any], list[Pose] | None, int]:
    """A real log's scans as the offline paths map them: de-skewed (:func:`deskewed`; ``check``:
    the order of their beams already judged, :func:`judged_sweep`), then a
    dense log's thinned by the motion filter, any other's all (``frontend``'s ``min_travel``,
    ``min_turn`` and ``dense_share``: :class:`mapping.lidar_frontend.FrontendConfig`), with
    their true poses when ``truth`` gives them. Returns ``(scans, truth, left out)``."""
    from mapping.lidar_frontend import dense_share, motion_filter

    scans = deskewed(scans, frontend, check)
    odometry = [s.odom for s in scans]
    if dense_share(odometry, frontend.min_travel, frontend.min_turn) <= frontend.dense_share:
        return list(scans), None if truth is None else list(truth), 0
    kept = motion_filter(odometry, frontend.min_travel, frontend.min_turn)
    kept_truth = None if truth is None else [truth[k] for k in kept]
    return [scans[k] for k in kept], kept_truth, len(scans) - len(kept)


#: Above these (m/s, rad/s) two scans' wheels are not a robot's motion (an odometry reset, a
#: clock jump): :func:`wheel_velocity` gives zero and the scan is not de-skewed.
MAX_SPEED, MAX_TURN_RATE = 10.0, 4.0 * math.pi
MIN_SCAN_GAP = 1e-3  # seconds: scans closer in time give no velocity


def wheel_velocity(before: Any, at: Any, after: Any) -> tuple[float, float, float]:
    """The wheels' velocity at scan ``at`` (``vx, vy`` m/s in its laser's frame, turn rad/s) from
    the scan ``before`` it to the scan ``after`` it (either may be ``at`` itself: a one-sided
    difference); zero when their times are less than ``MIN_SCAN_GAP`` apart or the velocity is
    beyond ``MAX_SPEED`` or ``MAX_TURN_RATE``."""
    dt = float(after.t) - float(before.t)
    return _velocity(at.odom.between(before.odom), at.odom.between(after.odom), dt)


def sweep_velocity(ls: Any) -> tuple[float, float, float] | None:
    """The wheels' velocity over scan ``ls``'s sweep (in its laser's frame, as
    :func:`wheel_velocity`) from the odometry at its first and last beam (``ls.odom``,
    ``ls.odom_end``); None when the reader had no odometry at the last beam."""
    if ls.odom_end is None:
        return None
    return _velocity(Pose(), ls.odom.between(ls.odom_end), ls.sweep)


def _velocity(back: Pose, on: Pose, dt: float) -> tuple[float, float, float]:
    """The velocity from pose ``back`` to pose ``on`` (both in the scan's laser frame) ``dt``
    seconds later; zero when ``dt`` is under ``MIN_SCAN_GAP`` or the velocity beyond
    ``MAX_SPEED`` or ``MAX_TURN_RATE``."""
    if not dt >= MIN_SCAN_GAP:
        return 0.0, 0.0, 0.0
    turn = math.remainder(on.theta - back.theta, 2.0 * math.pi) / dt
    vx, vy = (on.x - back.x) / dt, (on.y - back.y) / dt
    if not (math.hypot(vx, vy) <= MAX_SPEED and abs(turn) <= MAX_TURN_RATE):
        return 0.0, 0.0, 0.0
    return vx, vy, turn


def deskewed(scans: Sequence[Any], frontend: Any, check: SweepCheck | None = None) -> list[Any]:
    """``scans`` with the bearings of each whose beams were not simultaneous (its
    ``time_increment``) placed where the laser stood when each return came, at the wheels'
    velocity from it to the scan after it (the last scan: from the scan before it;
    :func:`wheel_velocity`, :func:`mapping.lidar_frontend.deskew`); all as they are when
    ``frontend.deskew`` is off; the beams in the order ``check`` says (by default
    :func:`judged_sweep`'s).

    Forwards, not centred on the scan: a scan's time is its first beam's (ROS's
    ``LaserScan`` convention), so its beams come during the motion that follows it, and a
    spinning lidar's sweep is the whole gap to the next scan. A velocity centred on the
    scan's time lags the sweep by half a scan: a 5 Hz lidar starting or ending a turn in
    place would be de-skewed by half its turn or twice it."""
    if not frontend.deskew:
        return list(scans)
    check = check if check is not None else judged_sweep(scans, frontend)
    rev = check.reversed if check is not None else bool(frontend.sweep_reversed)
    return [_deskewed_in(scans, k, rev) for k in range(len(scans))]


def _deskewed_in(scans: Sequence[Any], k: int, reversed_sweep: bool) -> Any:
    """Scan ``k`` of a log de-skewed at the wheels' velocity to the scan after it (the last
    scan: from the scan before it; :func:`deskewed`)."""
    ls = scans[k]
    if k + 1 < len(scans):
        return deskewed_scan(ls, ls, scans[k + 1], reversed_sweep)
    return deskewed_scan(ls, scans[max(k - 1, 0)], ls, reversed_sweep)


#: The order of a log's beams is judged on scans turning at least this fast (rad/s), at most
#: this many, and not with fewer than this many (``frontend.sweep_check``).
SWEEP_CHECK_TURN, SWEEP_CHECK_SCANS, SWEEP_CHECK_MIN = 0.3, 60, 10
#: A live robot judges it on at most this many scans as they came while it calibrates.
SWEEP_CHECK_KEEP = 400


@dataclass(frozen=True)
class SweepCheck:
    """:func:`sweep_check`'s finding: the order the de-skew takes the beams in (``reversed``:
    opposite to ``time_increment``'s sign), the turning scans it was judged on, and the inlier
    share per scan the order opposite to ``frontend.sweep_reversed`` gained over it (NaN:
    not judged)."""

    reversed: bool
    scans: int
    gain: float


def sweep_check(scans: Sequence[Any], frontend: Any) -> SweepCheck:
    """Which way a log's beams came (``frontend.sweep_check``): each turning scan (the wheels'
    velocity to the next scan at least ``SWEEP_CHECK_TURN``; the first ``SWEEP_CHECK_SCANS``)
    de-skewed as ``frontend.sweep_reversed`` says and the other way, each matched from the
    wheels' step against the scan before it de-skewed the same way; the other way is taken when
    it holds more of the points (its mean gain in inlier share at least 0.01 and three standard
    errors). ``frontend.sweep_reversed`` with fewer than ``SWEEP_CHECK_MIN`` turning scans."""
    from mapping.lidar_frontend import match_to_previous

    base = bool(frontend.sweep_reversed)
    n = len(scans)
    turning = [k for k in range(1, n - 1) if scans[k].time_increment and scans[k - 1].time_increment
               and abs(wheel_velocity(scans[k], scans[k], scans[k + 1])[2]) >= SWEEP_CHECK_TURN]
    turning = turning[:SWEEP_CHECK_SCANS]
    if len(turning) < SWEEP_CHECK_MIN:
        return SweepCheck(base, len(turning), math.nan)
    slam = for_scanner(frontend, scans).slam  # matched as the SLAM will match them

    def held(k: int, rev: bool) -> float:
        a, b = (_deskewed_in(scans, j, rev) for j in (k - 1, k))
        pa, pb = carmen_points([a, b], frontend)
        m = match_to_previous(pa, pb, a.odom.between(b.odom), slam)
        return 0.0 if m is None else m.inliers

    gain = np.array([held(k, not base) - held(k, base) for k in turning])
    mean, se = float(gain.mean()), float(gain.std(ddof=1) / math.sqrt(len(gain)))
    flip = mean >= 0.01 and mean > 3.0 * se
    return SweepCheck(base != flip, len(turning), mean)


def judged_sweep(scans: Sequence[Any], frontend: Any) -> SweepCheck | None:
    """The order the de-skew takes a log's beams in: None when nothing is de-skewed (the de-skew
    off, or no scan whose beams took time); judged on the log with ``frontend.sweep_check``
    (:func:`sweep_check`), else ``frontend.sweep_reversed`` (no scans judged)."""
    if not frontend.deskew or not any(s.time_increment for s in scans):
        return None
    if not frontend.sweep_check:
        return SweepCheck(bool(frontend.sweep_reversed), 0, math.nan)
    return sweep_check(scans, frontend)


def sweep_report(check: SweepCheck | None) -> dict[str, Any]:
    """:func:`judged_sweep`'s finding as report keys (none when nothing was de-skewed):
    ``sweep_reversed``, ``sweep_check_scans``, ``sweep_check_gain`` (None: not judged)."""
    if check is None:
        return {}
    return {"sweep_reversed": check.reversed, "sweep_check_scans": check.scans,
            "sweep_check_gain": check.gain if math.isfinite(check.gain) else None}


def deskewed_scan(ls: Any, before: Any, after: Any, reversed_sweep: bool = False) -> Any:
    """``ls`` de-skewed at the wheels' velocity over its sweep when its reader had the odometry
    at its last beam (:func:`sweep_velocity`), else from ``before`` to ``after``
    (:func:`wheel_velocity`; :func:`mapping.lidar_frontend.deskew`), its beams taken in the
    order opposite to its ``time_increment``'s with ``reversed_sweep``
    (``frontend.sweep_reversed``); itself when its beams are simultaneous."""
    from mapping.lidar_frontend import deskew

    if not ls.time_increment:
        return ls
    velocity = sweep_velocity(ls) or wheel_velocity(before, ls, after)
    ranges, angles = deskew(ls.ranges, ls.angles, -ls.time_increment if reversed_sweep else ls.time_increment,
                            velocity)
    return replace(ls, ranges=ranges, angles=angles, time_increment=0.0, odom_end=None)  # (de-skewed once)


def carmen_inputs(
    log: str | Sequence[Any],
    max_range: float | None = None,
    steps: int | None = None,
    truth: Sequence[Pose] | None = None,
    *,
    extract: Any = None,
    frontend: Any = None,
    yaw: float | None = None,
    calibration: LogCalibration | None = None,
    on_noise: Callable[[Any], None] | None = None,
) -> Iterator[ScanInput]:
    """Scans of a CARMEN log: each laser line's ranges through split-and-merge
    (:func:`mapping.extract.extract_corners`) and the raw points
    (:func:`mapping.lidar_frontend.scan_points`), odometry from consecutive odometry poses.

    Parameters
    ----------
    log : str or sequence of agents.files.carmen.LaserScan
        The log's path, or its scans already read by :func:`agents.files.carmen.read_carmen`.
    max_range : float, optional
        Cap on the scanner's range (metres): longer returns count as no return. Real scanners
        report up to 50-80 m; far, grazing returns make poor corners.
    steps : int, optional
        Stop after this many scans.
    truth : sequence of Pose, optional
        The true laser pose per scan (:func:`agents.files.carmen.scan_truth`), for ``true_pose``.
    extract : mapping.extract.ExtractConfig, optional
        Split-and-merge settings (its defaults without).
    frontend : mapping.lidar_frontend.FrontendConfig, optional
        Which returns become ``points`` (its defaults without).
    yaw : float, optional
        Turn every scan's bearings by ``-yaw`` radians (the laser's yaw); without, the front
        end's estimate when its ``yaw_calibration`` is on (:func:`calibrate_log`).
    calibration : LogCalibration, optional
        The (``steps``-long) log's calibrations already made (:func:`calibrate_log` with this
        ``frontend``); ``yaw`` is then not used.
    on_noise : callable, optional
        With the online SLAM (``frontend.slam.online``): given the wheels' heading noise when it
        is measured again during the run (:class:`mapping.lidar_frontend.OnlineSlam`),
        for a report of the prior the SLAM ended with.
    """
    from mapping.extract import ExtractConfig
    from mapping.lidar_frontend import FrontendConfig, scan_increment

    ecfg = extract if extract is not None else ExtractConfig()
    fcfg = frontend if frontend is not None else FrontendConfig()

    if isinstance(log, str):
        from agents.files.carmen import read_carmen

        scans: Sequence[Any] = read_carmen(log)
    else:
        scans = log
    if steps is not None:
        scans = scans[:steps]
    fcfg = for_scanner(fcfg, scans)
    cal = calibration if calibration is not None else calibrate_log(scans, fcfg, yaw)
    if len(cal.points) != len(scans):
        raise ValueError(f"calibration of {len(cal.points)} scans for {len(scans)} scans")
    pts, turn = cal.points, cal.turn
    wheels = [scaled(o, cal.scale) for o in wheel_increments(scans)]
    slam_odo: Iterator[Pose] | None = None  # the increments the filter gets from the lidar SLAM
    online = None
    if fcfg.slam.enabled and fcfg.slam.online:
        # Lidar SLAM scan by scan (mapping.lidar_slam): each increment as the SLAM gives it
        # when the scan comes, drawn as the scans are (and the graph's moves, follow_graph).
        from mapping.lidar_frontend import OnlineSlam

        online = OnlineSlam(fcfg, cal.noise, on_noise)
    elif fcfg.slam.enabled:
        # Lidar SLAM over the whole log first (mapping.lidar_slam); the filter then maps on its
        # smoothed increments.
        from mapping.lidar_frontend import slam_increments

        slam_odo = iter(slam_increments(pts, wheels, fcfg.slam, cal.noise)[0])
    prev_points: NDArray[np.float64] | None = None
    for k, ls in enumerate(scans):
        points = pts[k]
        odo = wheels[k]
        warp = None
        if online is not None:
            odo = online.add(points, odo)
            warp = online.warp
        elif slam_odo is not None:
            odo = next(slam_odo)
        elif fcfg.scan_odometry and prev_points is not None:
            # The wheel increment refined by the previous scan (mapping.lidar_frontend.scan_increment).
            odo = scan_increment(prev_points, points, odo, fcfg)[0]
        prev_points = points
        yield _scan_input(ls, max_range, turn, ecfg, odo, points, None if truth is None else truth[k], warp)


def _scan_input(
    ls: Any, max_range: float | None, turn: float, extract: Any, odometry: Pose, points: NDArray[np.float64],
    true_pose: Pose | None, warp: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> ScanInput:
    """One real scan's filter input: its corners (split-and-merge of the ranges, bearings turned
    by ``-turn``, returns at the scanner's or ``max_range``'s limit no return), the motion into
    it, its points to match and the SLAM's graph's move before it (``ScanInput.warp``)."""
    from mapping.extract import extract_corners

    rmax = float(ls.max_range) if max_range is None else min(float(ls.max_range), max_range)
    raw = np.asarray(ls.ranges, dtype=np.float64)
    angles = np.asarray(ls.angles, dtype=np.float64) - turn
    ranges = np.where(raw >= rmax, np.inf, raw)
    return ScanInput(float(ls.t), odometry, extract_corners(ranges, angles, rmax, extract), true_pose, points,
                     warp)


class LiveInputs:
    """Real scans that come one at a time (a robot's own lidar, live) as filter inputs, through a
    profile whose SLAM runs scan by scan (``lidar-slam-online``): what :func:`carmen_inputs`
    gives for the same scans, input for input (for scans whose beams are simultaneous: one
    whose beams took time is de-skewed here over its sweep or from the scan before it, offline
    from it to the scan after it, :func:`motion_filtered`) (and, with ``frontend.follow_graph``, each input
    after a loop moved the SLAM's graph carries the move: ``ScanInput.warp``).

    :meth:`add` takes a scan (:class:`agents.files.carmen.LaserScan`: ranges, bearings, time,
    the wheels' pose) and returns the inputs it made ready. The calibrations (the laser's yaw, the
    wheels' heading noise: :func:`calibrate_log`) rest on the first ``frontend.calibration_scans``
    scans, so those scans wait until the last of them has come (``calibrating`` is true
    meanwhile) and then come out together; every later scan comes out at once. :meth:`finish`
    calibrates on what came when the stream ends before that.

    **De-skew**: a scan whose beams took time (``time_increment``) is de-skewed first at the
    wheels' velocity over its sweep (``odom_end``: the live robot waits for the odometry past
    its last beam, :class:`agents.fleet.live_lidar.LiveLidar`), else since the scan that came
    before it (:func:`wheel_velocity` one-sided: a live robot has no scan after it yet, and
    that velocity lags the sweep by a scan; ``frontend.deskew``). The order of the beams is
    judged once, when the calibrations are made, on the scans that came meanwhile (consecutive,
    ``SWEEP_CHECK_KEEP`` at most; :func:`judged_sweep`, ``sweep``; the held scans are de-skewed
    again when it turns out the other way round); too few of them turning leaves
    ``frontend.sweep_reversed`` as set for the whole run.

    **Motion filter** (``min_travel`` metres, ``min_turn`` radians; 0 and 0 take every scan): a
    scan whose wheels are within those limits of the last scan taken
    (:func:`mapping.lidar_frontend.within_motion_limits`) is dropped before anything
    (``skipped`` counts them); a live lidar's stream is always dense
    (:class:`mapping.lidar_frontend.FrontendConfig`'s ``min_travel`` says why).

    Raises ``ValueError`` for a front end that needs the whole log first: a SLAM that is not
    ``online`` (``lidar-slam`` smooths over every scan before its first increment), or
    ``calibration_scans`` 0 (calibrations on every scan)."""

    def __init__(
        self, *, max_range: float | None, extract: Any, frontend: Any, yaw: float | None = None,
        on_noise: Callable[[Any], None] | None = None, min_travel: float = 0.0, min_turn: float = 0.0,
    ) -> None:
        from mapping.extract import ExtractConfig
        from mapping.lidar_frontend import FrontendConfig

        self.frontend = frontend if frontend is not None else FrontendConfig()
        self.extract = extract if extract is not None else ExtractConfig()
        if self.frontend.slam.enabled and not self.frontend.slam.online:
            raise ValueError("a live robot needs a SLAM that runs scan by scan (slam.online, the "
                             "lidar-slam-online profile): lidar-slam smooths over the whole log first")
        if self.frontend.calibration_scans <= 0:
            raise ValueError("a live robot calibrates on its first scans: frontend.calibration_scans "
                             "must be > 0 (0 means the whole log)")
        self.max_range = max_range
        self.yaw = yaw
        self.on_noise = on_noise
        self.calibration: LogCalibration | None = None
        self._holding: list[tuple[Any, Any]] = []  # the held scans as they came, with the scan before each
        self._came: list[Any] = []  # every scan as it came while calibrating (SWEEP_CHECK_KEEP at most)
        self.sweep: SweepCheck | None = None  # the beams' order, judged at the calibration
        self._turn_matrix: NDArray[np.float64] | None = None
        self._slam: Any = None
        self._prev_odom: Pose | None = None
        self._prev_points: NDArray[np.float64] | None = None
        if not (min_travel >= 0.0 and min_turn >= 0.0):
            raise ValueError(f"the motion filter's thresholds must be >= 0, got {min_travel}, {min_turn}")
        self.min_travel, self.min_turn = float(min_travel), float(min_turn)
        self._taken: Pose | None = None  # the wheels' pose of the last scan taken
        self._seen: Any = None  # the last scan that came (its time and wheels: the velocity)
        self.skipped = 0

    @property
    def calibrating(self) -> bool:
        return self.calibration is None

    @property
    def slam(self) -> Any:
        """The online SLAM (:class:`mapping.lidar_slam.LidarSlam`) once calibrated, else None."""
        return None if self._slam is None else self._slam.slam

    def add(self, ls: Any) -> list[ScanInput]:
        from mapping.lidar_frontend import within_motion_limits

        seen, self._seen = self._seen, ls
        if self.calibration is None and len(self._came) < SWEEP_CHECK_KEEP:
            self._came.append(ls)  # the beams' order is judged on consecutive scans
        # (the motion filter reads the wheels' pose, which the de-skew leaves as it is)
        if self._taken is not None and within_motion_limits(self._taken.between(ls.odom), self.min_travel,
                                                            self.min_turn):
            self.skipped += 1
            return []
        self._taken = ls.odom
        if self.calibration is None:  # held as it came: de-skewed once its beams' order is judged
            self._holding.append((ls, seen))
            if len(self._holding) < self.frontend.calibration_scans:
                return []
            return self._calibrate()
        ls = self._deskewed(ls, seen)
        return [self._next(ls, self._points_of(ls))]

    def finish(self) -> list[ScanInput]:
        """The held scans' inputs when the stream ended while calibrating (else none)."""
        return self._calibrate() if self.calibration is None and self._holding else []

    def _deskewed(self, ls: Any, seen: Any) -> Any:
        """A scan de-skewed as the front end says: over its sweep, else at the velocity since
        the scan ``seen`` before it (:func:`deskewed_scan`)."""
        if not self.frontend.deskew:
            return ls
        return deskewed_scan(ls, seen or ls, ls, self.frontend.sweep_reversed)

    @property
    def _held(self) -> list[Any]:
        """The scans held for the calibrations, de-skewed in the beams' order taken now."""
        return [self._deskewed(ls, seen) for ls, seen in self._holding]

    def _calibrate(self) -> list[ScanInput]:
        from mapping.lidar_frontend import OnlineSlam

        came, self._came = self._came, []
        self.sweep = judged_sweep(came, self.frontend)
        if self.sweep is not None and self.sweep.reversed != self.frontend.sweep_reversed:
            # the turning scans fit each other better the other way round: from now on
            self.frontend = replace(self.frontend, sweep_reversed=self.sweep.reversed)
        held, self._holding = self._held, []
        self.frontend = for_scanner(self.frontend, held)
        cal = calibrate_log(held, self.frontend, self.yaw)
        self.calibration = cal
        if cal.turn:
            c, s = math.cos(cal.turn), math.sin(cal.turn)
            self._turn_matrix = np.array([[c, -s], [s, c]])  # as calibrate_log turns the points
        if self.frontend.slam.enabled:
            self._slam = OnlineSlam(self.frontend, cal.noise, self.on_noise)
        return [self._next(ls, pts) for ls, pts in zip(held, cal.points, strict=True)]

    def _points_of(self, ls: Any) -> NDArray[np.float64]:
        pts = carmen_points([ls], self.frontend)[0]
        return pts if self._turn_matrix is None else pts @ self._turn_matrix

    def _next(self, ls: Any, points: NDArray[np.float64]) -> ScanInput:
        from mapping.lidar_frontend import scan_increment

        assert self.calibration is not None
        odo = Pose.identity() if self._prev_odom is None else self._prev_odom.between(ls.odom)
        odo = scaled(odo, self.calibration.scale)
        self._prev_odom = ls.odom
        warp = None
        if self._slam is not None:
            odo = self._slam.add(points, odo)
            warp = self._slam.warp
        elif self.frontend.scan_odometry and self._prev_points is not None:
            odo = scan_increment(self._prev_points, points, odo, self.frontend)[0]
        self._prev_points = points
        return _scan_input(ls, self.max_range, self.calibration.turn, self.extract, odo, points, None, warp)


def scan_fov(angles: Any) -> float:
    """Field of view (radians) covered by evenly spaced beam bearings."""
    a = np.asarray(angles, dtype=np.float64).reshape(-1)
    if len(a) < 2:
        return 2.0 * math.pi
    step = (a[-1] - a[0]) / (len(a) - 1)
    return float(min(2.0 * math.pi, a[-1] - a[0] + step))


def profiled_inputs(
    scans: Sequence[Any], profile: str, particles: int, threshold: float, max_range: float,
    overrides: Mapping[str, Any] | None = None,
) -> tuple[FilterConfig, Iterator[ScanInput]]:
    """Real scans through the real-lidar profile ``profile`` (a key of :data:`LIDAR_PROFILES`):
    the filter's settings (the profile's, then ``overrides``) and its inputs
    (:func:`carmen_inputs` with the profile's extractor and front end; with ``lidar-slam`` the
    SLAM runs over all of ``scans`` when the first input is drawn)."""
    settings, extract, frontend = split_profile(lidar_profile(profile))
    cfg = filter_config_for(particles, threshold, max_range, fov=scan_fov(scans[0].angles),
                            overrides={**settings, **(overrides or {})})
    return cfg, carmen_inputs(scans, max_range=max_range, extract=extract, frontend=frontend)


def feed(filt: WireframeFilter, inp: ScanInput) -> StepInfo:
    """One input's step of ``filt``; first, when the SLAM's graph moved (``inp.warp``), the map
    moved with it (:meth:`mapping.filter.WireframeFilter.warp`). The warp's nodes are in the
    SLAM's frame, whose first pose is the filter's ``origin``: the filter composes the SLAM's
    increments unchanged (no corner ICP, compass or loop closer of its own, as
    ``lidar-slam-online`` has it), so its map frame is the SLAM's moved by its origin."""
    if inp.warp is not None:
        from mapping.lidar_slam import graph_warp

        o = filt.origin
        c, s = math.cos(o.theta), math.sin(o.theta)

        def placed(nodes: NDArray[np.float64]) -> NDArray[np.float64]:  # origin composed with each node
            x, y = nodes[:, 0], nodes[:, 1]
            return np.column_stack([o.x + c * x - s * y, o.y + s * x + c * y, o.theta + nodes[:, 2]])

        then, now = inp.warp
        filt.warp(functools.partial(graph_warp, placed(then), placed(now)))
    return filt.step(inp.odometry, inp.scan, points=inp.points)


def run_filter(
    inputs: Iterable[ScanInput], filt: WireframeFilter, total: int | None = None
) -> Iterator[RunStep]:
    """Feed ``inputs`` to ``filt`` one by one and yield the state after each step."""
    for k, inp in enumerate(inputs):
        t0 = time.perf_counter()
        info = feed(filt, inp)
        dt = time.perf_counter() - t0
        yield RunStep(k, total, inp.t, inp.true_pose, filt.pose, inp.scan, filt, info, dt)


def robot_steps(opts: Any) -> Iterator[RunStep]:
    """The fleet robot's loop (:class:`agents.fleet.robot.RobotAgent`): simulate ``opts.world`` from
    ``opts.start`` along ``opts.route`` (planned from the start when None) and run a filter of
    ``opts.particles`` particles whose map frame is the robot's odometry frame (its first pose is
    the identity). ``opts.threshold`` is the merge threshold (``opts.resolution``, the wire
    quantisation, for options without one); ``opts.filter_overrides`` (dotted keys) go over
    both. ``opts.extra`` may set ``sensor`` (:data:`SENSORS`), ``scene_seed`` (the realistic
    lidar's scene; default ``opts.seed``) and ``max_range``; the sensor senses as far as the
    filter's ``max_range``. ``RunStep.true_pose`` is in the world frame."""
    from agents.sim.world import load_world

    world = load_world(opts.world)
    extra = dict(getattr(opts, "extra", {}) or {})
    threshold = float(getattr(opts, "threshold", opts.resolution))
    max_range = float(extra.get("max_range", 8.0))
    overrides = getattr(opts, "filter_overrides", None)
    cfg = filter_config_for(int(opts.particles), threshold, max_range, overrides=overrides)
    scene_seed = extra.get("scene_seed")
    options = SimOptions(
        sensor=str(extra.get("sensor", "corners")),
        max_range=cfg.max_range,
        duration=getattr(opts, "duration", None),
        scene_seed=None if scene_seed is None else int(scene_seed),
    )
    start = getattr(opts, "start", None)
    route = getattr(opts, "route", None)
    start_xy = None if start is None else (start.x, start.y)
    inputs = simulate(world, options, int(opts.seed), route=route, start=start_xy)
    filt = WireframeFilter(cfg, seeds_for(int(opts.seed))["filter"], initial_pose=Pose.identity())
    return run_filter(inputs, filt)


def sim_filter(
    world: Any, options: SimOptions, seed: int, particles: int, merge_threshold: float,
    config: FilterConfig | None = None,
) -> tuple[WireframeFilter, Iterator[ScanInput]]:
    """A filter whose map frame is the world frame (it starts at the first true pose) and the
    scans to feed it. ``config`` replaces ``filter_config_for(particles, merge_threshold,
    options.max_range)``."""
    inputs = simulate(world, options, seed)
    first = next(inputs)
    cfg = config if config is not None else filter_config_for(particles, merge_threshold, options.max_range)
    filt = WireframeFilter(cfg, seeds_for(seed)["filter"], initial_pose=first.true_pose)

    def chain() -> Iterator[ScanInput]:
        yield first
        yield from inputs

    return filt, chain()
