"""Real scanners' logs from the simulator: a world driven with a given scanner model, written
as a CARMEN log with its truth, so that the real-lidar path (``wiremap map --carmen``, ``wiremap
bench lidar``) maps it exactly as it maps a real log (``wiremap bench scanners``).

The shared real logs all come from one kind of scanner (a SICK LMS at 180 degrees, a scan
every 0.5-1 m of driving). Robots carry others: a 270-degree Hokuyo at 40 Hz, a 360-degree
RPLIDAR at 10 Hz, a TurtleBot3's 3.5 m LDS-01. :data:`SCANNERS` models them by what their data
sheets give (field of view, beams, range, rate); the realistic lidar
(:mod:`agents.sim.real_lidar`: range noise growing with range, dropouts, glass, clutter,
people) supplies what real scans have besides.

Choices
-------
* **Every scan the scanner sends** is written, at its rate while the robot drives at
  ``speed`` (0.5 m/s; a scan every 1.25 cm at 40 Hz): the log is as dense as a ROS bag of the
  robot, and the offline paths thin it (:func:`agents.mapping_run.motion_filtered`).
* **The robot turns in place** at the route's corners at ``TURN_RATE`` (1 rad/s): the scans
  keep coming while it turns, as they do on a real robot.
* **The wheels drift** about as the shared logs' do (their README: 5 % of distance, 2 degrees
  per metre), but smoothly and whatever the rate: real wheel odometry is smooth from one scan to
  the next and errs systematically (a wheel's radius, a slipping turn). The heading drifts at a
  rate (radians per metre) that wanders along the path (an Ornstein-Uhlenbeck process over the
  distance driven, stationary standard deviation ``ODOMETRY_ROT``, correlation length
  ``ODOMETRY_CORRELATION``), the distance is off by a scale error drawn once per log
  (``ODOMETRY_SCALE``), each step has a small jitter (``ODOMETRY_JITTER`` of its length) and a
  turn ``ODOMETRY_ROT_PER_RAD`` of itself. Noise drawn independently per step instead would
  shake a 40 Hz scanner's wheels far more than a 5 Hz one's.
* **A scan takes time** (``sweep``: a spinning lidar's turn, 0.1 s at 10 Hz; a Hokuyo's mirror
  sweeps 270 degrees in 19 ms): its beams are cast sector by sector (``SECTOR_S``, 10 ms a
  sector), each from the pose the robot had at that sector's time (moving from this scan's pose
  towards the next one's at the step's own speed), and the log says how far apart the beams
  came (``time_increment``, ROS's field; :func:`agents.files.carmen.write_carmen`). Turning on
  the spot at 1 rad/s, a 10 Hz scan's last beam is 5.7 degrees on from its first.
* **The laser sits at the robot's centre** (both FLASER poses are the wheels' pose); the truth
  file has the true pose of each scan, the log's own timestamps.
"""

from __future__ import annotations

import itertools
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agents.sim.lidar import LidarConfig
from mapping.se2 import Pose

__all__ = ["SCANNERS", "ScannerModel", "write_scanner_log"]

TURN_RATE = 1.0  # rad/s, turning in place at the route's corners
SECTOR_S = 0.01  # seconds of a scan's sweep cast from one pose
ODOMETRY_ROT = math.radians(1.0)  # rad/m, the heading's drift rate (stationary standard deviation)
ODOMETRY_CORRELATION = 2.0  # m driven over which the drift rate changes
ODOMETRY_SCALE = 0.03  # the distance's scale error (standard deviation, once per log)
ODOMETRY_JITTER = 0.01  # of each step's length, along and across
ODOMETRY_ROT_PER_RAD = 0.01  # rad per rad turned


@dataclass(frozen=True)
class ScannerModel:
    """A planar lidar as its data sheet gives it: ``fov`` degrees, ``beams`` per scan, ``max_range``
    metres, ``rate`` scans per second, ``sweep`` seconds from its first beam to its last."""

    name: str
    fov: float
    beams: int
    max_range: float
    rate: float
    sweep: float
    about: str

    def __post_init__(self) -> None:
        if not (0.0 < self.fov <= 360.0 and self.beams >= 2 and self.max_range > 0.0 and self.rate > 0.0
                and 0.0 <= self.sweep <= 1.0 / self.rate):
            raise ValueError(f"scanner {self.name}: need 0 < fov <= 360, beams >= 2, max_range > 0, "
                             f"rate > 0 and 0 <= sweep <= 1 / rate")

    @property
    def time_increment(self) -> float:
        """Seconds from one beam to the next."""
        return self.sweep / (self.beams - 1)


#: The scanners :func:`write_scanner_log` models (``wiremap bench scanners --scanners``).
SCANNERS: dict[str, ScannerModel] = {m.name: m for m in (
    ScannerModel("sick-lms", 180.0, 181, 20.0, 5.0, 180.0 / 360.0 / 75.0,
                 "SICK LMS 200/291 as in the shared CARMEN logs: 180 deg, 1 deg beams, capped at 20 m, "
                 "a 75 Hz mirror logged at 5 Hz"),
    ScannerModel("hokuyo-utm30", 270.0, 1081, 30.0, 40.0, 270.0 / 360.0 / 40.0,
                 "Hokuyo UTM-30LX: 270 deg, 0.25 deg beams, 30 m, 40 Hz"),
    ScannerModel("hokuyo-urg04", 240.0, 683, 5.6, 10.0, 240.0 / 360.0 / 10.0,
                 "Hokuyo URG-04LX: 240 deg, 0.35 deg beams, 5.6 m, 10 Hz"),
    ScannerModel("rplidar-a2", 360.0, 400, 12.0, 10.0, 0.1 * 399 / 400,
                 "Slamtec RPLIDAR A2: 360 deg, 0.9 deg beams, 12 m, spinning at 10 Hz"),
    ScannerModel("lds-01", 360.0, 360, 3.5, 5.0, 0.2 * 359 / 360,
                 "TurtleBot3's LDS-01: 360 deg, 1 deg beams, 3.5 m, spinning at 5 Hz"),
)}


def write_scanner_log(
    world: str, model: ScannerModel, seed: int, path: str | os.PathLike[str], *, duration: float,
    speed: float = 0.5, reversed_sweep: bool = False,
) -> int:
    """Drive ``world`` (a built-in name or a world file) for ``duration`` seconds along its
    coverage route (drawn from ``seed``) at ``speed`` m/s with ``model``'s scanner; write every
    scan as the CARMEN log ``path`` (``NAME.log``, or ``NAME.log.gz`` compressed) and the true poses beside it
    (``NAME.truth.tsv``, :func:`agents.files.carmen.truth_path_for`). The same arguments give
    the same files. ``reversed_sweep``: the beams are cast last bearing first while the log
    says first bearing first (a positive ``time_increment``), as the TurtleBot3 LDS-01's ROS
    driver writes them by default. Returns the number of scans.

    Raises
    ------
    ValueError
        ``duration`` or ``speed`` not positive, or a world the route planner cannot drive.
    """
    from agents.files.carmen import LaserScan, flaser_angles, truth_path_for, write_carmen
    from agents.files.io import write_atomic
    from agents.mapping_run import seeds_for
    from agents.sim.motion import OdometryNoise, drive
    from agents.sim.real_lidar import RealLidarConfig, build_scene, realistic_scan
    from agents.sim.route import plan_route
    from agents.sim.world import load_world

    if not (duration > 0.0 and speed > 0.0):
        raise ValueError(f"need duration > 0 and speed > 0, got {duration} and {speed}")
    w = load_world(world)
    rngs = seeds_for(seed)
    route = plan_route(w, rngs["route"], sensor_range=min(model.max_range, 8.0))
    steps = drive(route, speed=speed, dt=1.0 / model.rate, noise=OdometryNoise.none(), rng=rngs["drive"],
                  max_turn_rate=TURN_RATE)
    steps = [s for s in steps if s.t <= duration + 1e-9]
    fov = math.radians(model.fov)
    lidar = LidarConfig(beams=model.beams, fov=fov, max_range=model.max_range)
    real = RealLidarConfig()
    scene = build_scene(w, real.scene, seed).clear_of(route, real.scene.route_clearance)
    angles = flaser_angles(model.beams, fov)
    scans: list[LaserScan] = []
    wheels = Wheels(rngs["drive"])
    pose = steps[0].true_pose
    previous = steps[0].true_pose
    sectors = _sectors(lidar, model)
    if reversed_sweep:
        sectors = [(lo, hi, cfg, bearing, model.sweep - delay) for lo, hi, cfg, bearing, delay in sectors]
    for k, s in enumerate(steps):
        pose = pose.compose(wheels.step(previous.between(s.true_pose)))
        previous = s.true_pose
        motion = s.true_pose.between(steps[min(k + 1, len(steps) - 1)].true_pose)  # over 1 / rate seconds
        ranges = np.empty(model.beams)
        for lo, hi, cfg, bearing, delay in sectors:
            f = delay * model.rate  # the share of the step's motion done when the sector is cast
            at = s.true_pose.compose(Pose(f * motion.x, f * motion.y, f * motion.theta + bearing))
            ranges[lo:hi] = realistic_scan(scene, at, s.t + delay, cfg, real.noise, rngs["sensor"])
        scans.append(LaserScan(s.t, ranges, angles, model.max_range, pose,
                               time_increment=model.time_increment))
    write_carmen(path, scans, fov=fov, max_range=model.max_range, time_increment=model.time_increment,
                 comment=f"wiremap simulated {model.name} ({model.about}) in {w.name}, seed {seed}")
    rows = "".join(f"{s.t:.6f} {p.x:.6f} {p.y:.6f} {p.theta:.6f}\n"
                   for s, p in zip(steps, (st.true_pose for st in steps), strict=True))
    write_atomic(truth_path_for(path), "# t x y theta (true pose of each FLASER line)\n" + rows)
    return len(scans)


def _sectors(lidar: LidarConfig, model: ScannerModel) -> list[tuple[int, int, LidarConfig, float, float]]:
    """A scan's beams cut into sectors of about ``SECTOR_S`` seconds of its sweep: per sector its
    beams ``[lo, hi)``, a lidar of just those beams centred on the robot's heading, the bearing
    of their centre and the seconds from the scan's first beam to the sector's middle."""
    count = min(max(1, math.ceil(model.sweep / SECTOR_S)), model.beams // 2)
    bounds = np.linspace(0, model.beams, count + 1).round().astype(int)
    angles = lidar.angles()
    step = float(angles[1] - angles[0])
    out = []
    for lo, hi in itertools.pairwise(bounds.tolist()):
        cfg = LidarConfig(beams=hi - lo, fov=(hi - lo - 1) * step, max_range=lidar.max_range)
        centre = 0.5 * float(angles[lo] + angles[hi - 1])
        out.append((lo, hi, cfg, centre, 0.5 * (lo + hi - 1) * model.time_increment))
    return out


class Wheels:
    """Drifting wheel odometry (the module's choices): :meth:`step` turns a true increment into
    the wheels' account of it."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.scale = 1.0 + ODOMETRY_SCALE * float(rng.standard_normal())
        self.rate = ODOMETRY_ROT * float(rng.standard_normal())  # rad/m, now

    def step(self, true: Pose) -> Pose:
        d = math.hypot(true.x, true.y)
        e = self.rng.standard_normal(4)
        keep = math.exp(-d / ODOMETRY_CORRELATION)  # the drift rate's memory over d metres
        self.rate = keep * self.rate + ODOMETRY_ROT * math.sqrt(1.0 - keep * keep) * float(e[0])
        jitter = ODOMETRY_JITTER * d
        return Pose(self.scale * true.x + jitter * e[1], self.scale * true.y + jitter * e[2],
                    true.theta + self.rate * d + ODOMETRY_ROT_PER_RAD * abs(true.theta) * e[3])


def log_name(world: str, model: ScannerModel, seed: int) -> str:
    """``office-lds-01-s1``: the log's name for a world, scanner and seed."""
    return f"{Path(world).stem if os.sep in world else world}-{model.name}-s{seed}"
