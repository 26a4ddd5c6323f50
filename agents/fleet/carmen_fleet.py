"""Real logs as fleets: a CARMEN log split into N robots (``wiremap run --carmen LOG --robots N``).

Robot ``k`` replays scans ``[i0, i1)`` of the log (:func:`split`: N stretches of equal length
along the log, each running on into the next by ``overlap`` of a stretch, so that neighbours
see common walls) through its own particle filter, in its own odometry frame starting at the
origin (the first scan of its stretch is the identity), and publishes with an unknown origin:
only global registration can put the robots together. Its scans go through the real-lidar
profile ``--lidar-profile`` as in ``wiremap map --carmen`` (default ``lidar-slam``: the robot
runs the lidar SLAM over its whole stretch before it maps, as a replay can; the filter's
defaults, which these robots used before, are the simulator's and map real scans poorly).

Scoring (:func:`score_map`): a map in some robot's frame is placed in the log's truth frame by
that robot's true first pose (``NAME.truth.tsv``, one row per laser line) -- no fitting -- and
its *endpoint precision* is the fraction of points sampled every 5 cm along its walls that lie
within 0.2 m of a real scan endpoint placed at its truth pose (the data README's measure).

The log is read by :func:`agents.files.carmen.read_carmen_log` and scored with
:mod:`mapping.lidar_metrics`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapping.se2 import Pose
from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]

MAX_RANGE = 20.0  # as `wiremap map --carmen`
ENDPOINT_TOL = 0.2
SAMPLE_STEP = 0.05


def read_log(
    path: str | os.PathLike[str], bag: dict[str, Any] | None = None, profile: str | None = None
) -> list[Any]:
    """The log's laser scans (:func:`agents.files.carmen.read_carmen_log`; unreadable lines
    skipped); with ``bag`` (its topics: ``scan_topic``, ``odom_topic``, ``truth_topic``) the ROS
    bag's (:func:`agents.files.rosbag.read_rosbag`; unreadable messages skipped; with a truth
    topic, the scans without a true pose left out, as ``wiremap run`` reads the bag). With a
    real-lidar ``profile``, a dense log's thinned by its motion filter, as ``wiremap run``'s
    service thins it (:func:`thinned`)."""
    if bag is not None:
        from agents.files.rosbag import read_rosbag

        rb = read_rosbag(path, scan_topic=bag.get("scan_topic"), odom_topic=bag.get("odom_topic"),
                         truth_topic=bag.get("truth_topic"))
        scans = list(rb.scans)
    else:
        from agents.files.carmen import read_carmen_log

        scans = list(read_carmen_log(path).scans)
    return scans if profile is None else thinned(scans, None, profile)[0]


def thinned(scans: list[Any], truth: list[Pose] | None, profile: str) -> tuple[list[Any], list[Pose] | None]:
    """A fleet's log as its robots map it: a dense log's scans (and true poses) thinned by the
    motion filter of the real-lidar ``profile`` (:func:`agents.mapping_run.motion_filtered`)."""
    from agents import mapping_run as mr

    kept, kept_truth, _ = mr.motion_filtered(scans, truth, mr.split_profile(mr.lidar_profile(profile))[2])
    return kept, kept_truth


def split(n_scans: int, robots: int, overlap: float = 0.3) -> list[tuple[int, int]]:
    """``robots`` stretches ``[i0, i1)`` of equal length along ``n_scans`` scans, each running
    on into the next by ``overlap`` of a stretch."""
    if robots < 1 or n_scans < robots:
        raise ValueError(f"cannot split {n_scans} scans among {robots} robots")
    piece = n_scans / robots
    out = []
    for k in range(robots):
        i0 = round(k * piece)
        i1 = min(n_scans, round((k + 1) * piece + overlap * piece))
        out.append((i0, i1))
    return out


def robot_steps(opts: Any) -> Iterator[Any]:
    """The robot's loop (:func:`agents.mapping_run.run_filter`) over scans ``opts.scans`` of
    ``opts.carmen`` (a ROS bag with ``opts.extra["rosbag"]``) through the real-lidar profile
    ``opts.lidar_profile``, its filter starting at the identity (its own odometry frame)."""
    from agents import mapping_run as mr
    from mapping.filter import WireframeFilter

    scans = read_log(opts.carmen, opts.extra.get("rosbag"), opts.lidar_profile)
    i0, i1 = opts.scans if opts.scans is not None else (0, len(scans))
    part = scans[i0:i1]
    if not part:
        raise ValueError(f"no scans in {i0}:{i1} of {opts.carmen}")
    max_range = min(float(part[0].max_range), MAX_RANGE)
    # The real-lidar profile as `wiremap map --carmen` applies it (the user's settings on top);
    # with lidar-slam the SLAM runs over the whole stretch before the first map is published.
    cfg, inputs = mr.profiled_inputs(part, opts.lidar_profile, int(opts.particles), float(opts.threshold),
                                     max_range, opts.filter_overrides)
    filt = WireframeFilter(cfg, mr.seeds_for(int(opts.seed))["filter"], initial_pose=Pose.identity())
    return mr.run_filter(inputs, filt, total=len(part))


def endpoints(scans: list[Any], truth: list[Pose], max_range: float = MAX_RANGE) -> FloatArray:
    """Every scan's endpoints (returns under ``max_range``) placed at its truth pose."""
    from mapping.lidar_metrics import scan_endpoints

    k = min(len(scans), len(truth))
    return scan_endpoints(
        [(p.x, p.y, p.theta) for p in truth[:k]],
        [ls.ranges for ls in scans[:k]],
        [ls.angles for ls in scans[:k]],
        max_range=min([max_range] + [float(ls.max_range) for ls in scans[:1]]),
    ) if k else np.zeros((0, 2))


def endpoint_precision(
    wf: Wireframe, ends: FloatArray, tol: float = ENDPOINT_TOL, step: float = SAMPLE_STEP
) -> float:
    """Fraction of points every ``step`` along the walls within ``tol`` of an endpoint
    (:func:`mapping.lidar_metrics.map_precision`)."""
    from mapping.lidar_metrics import map_precision

    return map_precision(wf, ends, tol, step)


#: A registration whose transform is off by more than this (metres, degrees) is wrong: a false
#: merge when accepted (``wiremap bench register``, the runs' ``registration_truth``).
WRONG_M, WRONG_DEG = 0.5, 2.0


def local_truth(fa: Any, fb: Any, start: Pose) -> Pose:
    """The true transform of map ``b``'s frame in map ``a``'s *where they share walls* (``fa``,
    ``fb``: their :func:`mapping.registration.prepare` features). Maps made by robots drift, so
    the transform between their true start poses misplaces the walls far from the starts (by
    both robots' drift, up to a metre over a log's stretch); the local truth starts there and is
    refined on the two maps' walls (:func:`mapping.registration.refine`, the gate annealed from
    1.5 m down): the alignment of the walls both maps hold that is nearest the start poses'
    truth."""
    from mapping.registration import RegistrationConfig, refine

    return refine(fa, fb, start, RegistrationConfig(coarse_match_dist=1.5, refine_iterations=15))


def shared_wall(a_samples: FloatArray, b: Wireframe, transform: Pose, tol: float = 0.2) -> float:
    """Metres of map ``b``'s walls (placed by ``transform``) within ``tol`` of one of map ``a``'s
    wall samples ``a_samples`` (:func:`mapping.metrics.sample_walls`): how much the two maps
    share there (``b`` sampled every 0.1 m)."""
    from mapping.lidar_metrics import map_precision

    if len(a_samples) == 0 or b.n_edges == 0:
        return 0.0
    return map_precision(b.transformed(transform), a_samples, tol, 0.1) * b.total_length()


def error_at(found: Pose, true: Pose, point: FloatArray) -> tuple[float, float]:
    """Translation (m) at ``point`` (in the frame both poses place) and rotation (radians)
    between two placements ``found`` and ``true`` of a map: taken at the centre of its walls,
    how far a registration puts the walls from where ``true`` does, rather than its origin (far
    from the walls, a small turn moves the origin a lot)."""
    d = found.apply(point[None, :])[0] - true.apply(point[None, :])[0]
    return float(math.hypot(*d)), abs(math.remainder(found.theta - true.theta, 2 * math.pi))


def pose_error(found: Pose, true: Pose) -> tuple[float, float]:
    """Translation (m) and rotation (deg) error of a registered pose."""
    return (
        math.hypot(found.x - true.x, found.y - true.y),
        math.degrees(abs(math.remainder(found.theta - true.theta, 2 * math.pi))),
    )
