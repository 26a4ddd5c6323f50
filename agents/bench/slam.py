"""``wiremap bench slam``: the lidar SLAM alone (:mod:`mapping.lidar_slam`) on real CARMEN logs,
from several start frames.

The SLAM's correlative loop search runs on an axis-aligned grid, so its result depends a little
on the frame the log is replayed in; on a real log one loop more or less moves the trajectory by
decimetres. A single run is one draw: this bench replays each log from ``--starts K`` frames
(the origin, as ``wiremap map`` and ``wiremap bench lidar`` do; the true first pose; then frames
drawn from ``--seed``), maps each result into the truth's frame by the rigid transform between
the start used and the true first pose, and reports per log the **median** over the starts.

Scores per log: ``ate_rmse_m`` (median over starts; each start's in ``ate_rmse_m_by_start``),
``ate_max_m``, ``rpe_1m_m`` (:mod:`mapping.lidar_metrics`), ``loops`` (loops closed online,
median), ``ms_per_scan`` (CPU of the SLAM, online pass and :meth:`~mapping.lidar_slam.LidarSlam.refine`),
``odometry_ate_rmse_m``, ``odo_rot_per_m`` (the SLAM's heading prior per metre as it ran: with
``slam.odo_calibration``, fitted to the log's own wheels). Settings: the ``lidar-slam``
profile's front end with any ``--set slam.KEY=VALUE`` / ``frontend.KEY=VALUE`` on top.

Output: an aligned table, and with ``--json`` one last line::

    {"logs": {NAME: {...}}, "median": {...}, "worst_ate_rmse_m": M, "starts": K, "settings": {...}}
"""

from __future__ import annotations

import argparse
import json
import math
import time
from typing import Any, NamedTuple

import numpy as np

from agents.argtypes import non_negative_int
from agents.bench.common import aligned_rows, fmt_cell
from agents.bench.lidar import add_log_arguments, find_logs, log_name, settings_for
from agents.errors import UserError

HELP = "the lidar SLAM alone on real CARMEN logs, median over several start frames"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_log_arguments(parser)
    parser.add_argument("--starts", type=int, default=4, metavar="K",
                        help="start frames per log (default 4: origin, true start, 2 drawn)")
    parser.add_argument("--seed", type=non_negative_int, default=1,
                        help="seed of the drawn start frames (default 1)")
    parser.add_argument("--jobs", type=int, default=1, metavar="N", help="runs at once (default 1)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                        help="override one setting (e.g. slam.refine_passes=0); repeatable")
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")


def start_frames(k: int, seed: int) -> list[tuple[float, float, float] | None]:
    """``k`` start frames: the origin, ``None`` (the true first pose), then drawn from ``seed``
    (position within 50 m, any heading)."""
    rng = np.random.default_rng(seed)
    out: list[tuple[float, float, float] | None] = [(0.0, 0.0, 0.0), None]
    while len(out) < k:
        x, y = rng.uniform(-50.0, 50.0, 2)
        out.append((float(x), float(y), float(rng.uniform(-math.pi, math.pi))))
    return out[:k]


class SlamRun(NamedTuple):
    """One log's SLAM run (:func:`slam_over_log`): the log's scans, its truth, the calibration
    the front end measured, the SLAM (its poses in the start frame's), the start frame used and
    the SLAM's CPU seconds."""

    scans: list[Any]
    truth: list[Any]
    cal: Any
    slam: Any
    start: Any
    cpu_s: float


def slam_over_log(path: str, settings: dict[str, Any],
                  start: tuple[float, float, float] | None = None) -> SlamRun:
    """The ``settings``' front end's SLAM over one CARMEN log (that has a truth) from ``start``
    (None: the true first pose), calibrated as ``wiremap bench lidar`` calibrates it."""
    from agents import mapping_run as mr
    from agents.files.carmen import read_carmen_log, scan_truth
    from mapping.lidar_frontend import run_slam
    from mapping.se2 import Pose

    _, _, fcfg = mr.split_profile(settings)
    log = read_carmen_log(path)
    truth = scan_truth(log)
    if truth is None:
        raise UserError(f"{path}: no truth (NAME.truth.tsv or TRUEPOS lines)")
    scans, kept_truth, _ = mr.motion_filtered(log.scans, truth, fcfg)  # a dense log thinned
    assert kept_truth is not None
    truth = kept_truth
    fcfg = mr.for_scanner(fcfg, scans)
    cal = mr.calibrate_log(scans, fcfg)
    st = truth[0] if start is None else Pose(*start)
    t0 = time.process_time()
    wheels = [mr.scaled(o, cal.scale) for o in mr.wheel_increments(scans)]
    slam = run_slam(cal.points, wheels, fcfg.slam, start=np.array(st.as_tuple()),
                    noise=cal.noise)
    return SlamRun(scans, truth, cal, slam, st, time.process_time() - t0)


def run_one(path: str, start: tuple[float, float, float] | None, settings: dict[str, Any]) -> dict[str, Any]:
    """The SLAM over one log from one start frame, scored in the truth's frame; the odometry's
    error as ``wiremap bench lidar`` gives it (the log's own poses)."""
    from agents import mapping_run as mr
    from agents.bench.lidar import pose_array
    from mapping.lidar_metrics import ate, rpe
    from mapping.se2 import Pose

    scans, truth, cal, slam, st, cpu = slam_over_log(path, settings, start)
    to_truth = truth[0].compose(st.inverse())
    est = np.array([to_truth.compose(Pose(*map(float, p))).as_tuple() for p in slam.scan_poses()])
    tr = pose_array(truth)
    rmse, mx = ate(est, tr)
    return {"ate_rmse_m": rmse, "ate_max_m": mx, "rpe_1m_m": rpe(est, tr), "loops": len(slam.loops),
            "ms_per_scan": 1000.0 * cpu / max(1, len(scans)), "scans": len(scans),
            "odometry_ate_rmse_m": ate(pose_array([s.odom for s in scans]), tr)[0],
            "odo_rot_per_m": slam.config.odo_rot_per_m, **mr.yaw_report(cal)}


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One log's runs (one per start): medians, and every start's ATE."""
    out: dict[str, Any] = {k: round(float(np.median([r[k] for r in runs])), 6)
                           for k in ("ate_rmse_m", "ate_max_m", "rpe_1m_m", "loops", "ms_per_scan",
                                     "odometry_ate_rmse_m")}
    out["scans"] = runs[0]["scans"]
    out["laser_yaw_deg"] = round(float(runs[0]["laser_yaw_deg"]), 6)  # the same from every start
    # The heading prior the SLAM ran with (rad/m; with slam.odo_calibration, fitted to the log's
    # wheels: the same from every start).
    out["odo_rot_per_m"] = round(float(runs[0]["odo_rot_per_m"]), 6)
    out["ate_rmse_m_by_start"] = [round(float(r["ate_rmse_m"]), 6) for r in runs]
    return out


def run(args: argparse.Namespace) -> int:
    from concurrent.futures import ProcessPoolExecutor

    if args.starts < 1:
        raise UserError(f"--starts must be >= 1, got {args.starts}")
    if args.jobs < 1:
        raise UserError(f"--jobs must be >= 1, got {args.jobs}")
    paths = find_logs(list(args.logs), args.data)
    settings = settings_for("lidar-slam", list(args.sets))
    starts = start_frames(args.starts, args.seed)
    logs_in = [str(p) for p in paths for _ in starts]
    starts_in = starts * len(paths)
    same = [settings] * len(logs_in)
    if args.jobs == 1:
        done = list(map(run_one, logs_in, starts_in, same))
    else:
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            done = list(pool.map(run_one, logs_in, starts_in, same))
    logs: dict[str, dict[str, Any]] = {}
    for i, p in enumerate(paths):
        logs[log_name(p)] = summarise(done[i * len(starts):(i + 1) * len(starts)])
    keys = ("ate_rmse_m", "ate_max_m", "rpe_1m_m", "ms_per_scan", "odometry_ate_rmse_m")
    med = {k: round(float(np.median([r[k] for r in logs.values()])), 6) for k in keys}
    head = ["log", "scans", "ATE m (median)", "ATE by start", "max m", "RPE 1 m", "loops", "ms/scan",
            "odo ATE"]
    m3, m1 = "{:.3f}", "{:.1f}"
    rows = [[n, str(r["scans"]), fmt_cell(r["ate_rmse_m"], m3),
             " ".join(f"{a:.3f}" for a in r["ate_rmse_m_by_start"]),
             fmt_cell(r["ate_max_m"], m3), fmt_cell(r["rpe_1m_m"], m3), fmt_cell(r["loops"], "{:.0f}"),
             fmt_cell(r["ms_per_scan"], m1), fmt_cell(r["odometry_ate_rmse_m"], m3)] for n, r in logs.items()]
    rows.append(["median", "", fmt_cell(med["ate_rmse_m"], m3), "", fmt_cell(med["ate_max_m"], m3),
                 fmt_cell(med["rpe_1m_m"], m3), "", fmt_cell(med["ms_per_scan"], m1),
                 fmt_cell(med["odometry_ate_rmse_m"], m3)])
    print(aligned_rows([head, *rows]))
    if args.json:
        worst = max(r["ate_rmse_m"] for r in logs.values())
        print(json.dumps({"logs": logs, "median": med, "worst_ate_rmse_m": worst, "starts": len(starts),
                          "settings": settings}))
    return 0

