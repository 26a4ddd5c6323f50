"""A development measurement (not a test): a CARMEN log fed to the live mapper's input stage one
scan at a time (:class:`agents.mapping_run.LiveInputs`, the ``lidar-slam-online`` profile), with
and without its motion filter; the online SLAM's poses integrated from the truth's first pose,
ATE over the scans mapped.

``python tests/live_ate.py LOG [LOG ...] [--filter M,DEG ...] [--calibration N] [--set KEY=VALUE
...] [--sweep-odometry]`` (default filter 0.5,10; 100 scans held for the
calibrations; ``--set`` over the profile; ``--sweep-odometry``: each scan whose beams took time
carries the wheels' pose at its last beam, interpolated between the log's scans, as a live robot
pairs it from its odometry stream).
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

import numpy as np

from agents import mapping_run as mr
from agents.files.carmen import read_carmen_log, scan_truth


def live_log(
    path: str, calibration: int, sets: dict[str, Any] | None = None
) -> tuple[list[Any], list[Any], dict[str, Any], Any, Any]:
    """A log with a truth, and the live robot's profile (``lidar-slam-online``, ``calibration``
    scans held, ``sets`` over it): ``(scans, truth, filter overrides, extractor, front end)``."""
    log = read_carmen_log(path)
    truth = scan_truth(log)
    if truth is None:
        raise SystemExit(f"{path}: no truth")
    fo, extract, frontend = mr.split_profile({**mr.lidar_profile("lidar-slam-online"),
                                              "frontend.calibration_scans": calibration, **(sets or {})})
    return list(log.scans), truth, fo, extract, frontend


def with_sweep_odometry(scans: list[Any]) -> list[Any]:
    """``scans`` with ``odom_end`` where their beams took time: the wheels' pose at the last beam,
    interpolated between the scans' own (as :class:`agents.fleet.live_lidar.LiveLidar` pairs it
    from an odometry stream at least as fast as the scans)."""
    from dataclasses import replace

    from agents.files.rosbag import interpolate

    stamps = np.array([s.t for s in scans], dtype=np.float64)
    odom = [s.odom for s in scans]
    return [replace(s, odom_end=interpolate(stamps, odom, s.t + s.sweep)) if s.sweep else s for s in scans]


def run(
    path: str, min_travel: float, min_turn_deg: float, calibration: int = 100,
    sets: dict[str, str] | None = None, sweep_odometry: bool = False,
) -> tuple[int, int, float, float]:
    """``(scans mapped, scans left out, ATE m, CPU ms per scan)``."""
    scans, truth, _, extract, frontend = live_log(path, calibration, sets)
    if sweep_odometry:
        scans = with_sweep_odometry(scans)
    live = mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend, min_travel=min_travel,
                         min_turn=math.radians(min_turn_deg))
    waiting: list[int] = []  # the scans taken, in order, whose inputs have not come out yet
    est = []
    pose = None
    t0 = time.process_time()

    def take(inputs: list[mr.ScanInput]) -> None:
        nonlocal pose
        for inp in inputs:
            j = waiting.pop(0)
            pose = truth[j] if pose is None else pose.compose(inp.odometry)
            est.append((j, pose))

    for k, ls in enumerate(scans):
        before = live.skipped
        out = live.add(ls)
        if live.skipped == before:
            waiting.append(k)
        take(out)
    take(live.finish())
    ms = (time.process_time() - t0) / max(1, len(scans)) * 1e3
    err = [math.hypot(p.x - truth[j].x, p.y - truth[j].y) for j, p in est]
    return len(est), live.skipped, float(np.sqrt(np.mean(np.square(err)))), ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="+")
    ap.add_argument("--filter", action="append", metavar="M,DEG", help="motion filter thresholds (repeat)")
    ap.add_argument("--calibration", type=int, default=100, help="scans held for the calibrations")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                    help="a setting over the profile's (e.g. slam.loop_settled_xy=0)")
    ap.add_argument("--sweep-odometry", action="store_true",
                    help="each scan carries the wheels' pose at its last beam (a live robot's odometry)")
    args = ap.parse_args()
    sets = dict(item.split("=", 1) for item in args.sets)
    filters = [tuple(float(v) for v in f.split(",")) for f in (args.filter or ["0.5,10"])]
    for path in args.logs:
        name = path.split("/")[-1].split(".")[0]
        n, _, ate, _ = run(path, 0.0, 0.0, args.calibration, sets, args.sweep_odometry)
        line = f"{name:14s} every scan: {n} mapped, ATE {ate:.3f} m"
        for d, a in filters:
            n, still, ate, ms = run(path, d, a, args.calibration, sets, args.sweep_odometry)
            line += (f" | {d:g} m / {a:g} deg: {n} mapped ({still} left out), ATE {ate:.3f} m, "
                     f"{ms:.1f} ms/scan")
        print(line, flush=True)


if __name__ == "__main__":
    main()
