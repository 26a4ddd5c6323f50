"""Where the lidar SLAM's heading goes wrong on a real log (``python tests/slam_heading.py
LOG...``): the ``lidar-slam`` profile's SLAM over each CARMEN log from the true first pose (as
``wiremap bench lidar`` runs it), then, against the truth beside the log, its ATE, the heading
error every tenth of the log, and each step's turn error (the SLAM's turn between two scans less
the truth's): its RMS, its sum, and the steps off by more than 0.7 degree with the truth's turn
and the wheels' error on the same step.

A development measurement (figures in ``docs/experiments.md``), not a benchmark.
"""

from __future__ import annotations

import argparse

import numpy as np


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def main() -> None:
    from agents import mapping_run as mr
    from agents.bench.lidar import pose_array, settings_for
    from agents.files.carmen import read_carmen_log, scan_truth
    from mapping.lidar_frontend import run_slam
    from mapping.lidar_metrics import ate

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", nargs="+", metavar="LOG")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets")
    args = ap.parse_args()
    _, _, fcfg = mr.split_profile(settings_for("lidar-slam", list(args.sets)))
    for path in args.logs:
        log = read_carmen_log(path)
        truth = scan_truth(log)
        if truth is None:
            raise SystemExit(f"{path}: no truth beside it")
        cal = mr.calibrate_log(log.scans, fcfg)
        slam = run_slam(cal.points, mr.wheel_increments(log.scans), fcfg.slam,
                        start=np.array(truth[0].as_tuple()), noise=cal.noise)
        est, tr = np.asarray(slam.poses), pose_array(truth)
        odo = pose_array([s.odom for s in log.scans])
        heading = _wrap_deg(np.degrees(est[:, 2] - tr[:, 2]))
        turn_t, turn_e, turn_o = (_wrap_deg(np.degrees(np.diff(p[:, 2]))) for p in (tr, est, odo))
        err, odo_err = turn_e - turn_t, turn_o - turn_t
        big = np.flatnonzero(np.abs(err) > 0.7)
        print(f"{path}: ATE {ate(est, tr)[0]:.3f} m, {len(slam.loops)} loops; step turn error RMS "
              f"{np.sqrt(np.mean(err ** 2)):.2f} deg, sum {err.sum():+.2f} deg, {len(big)} of {len(err)} "
              "steps off by > 0.7 deg")
        every = max(1, len(est) // 10)
        marks = range(0, len(est), every)
        print("  heading error by scan: " + ", ".join(f"{i} {heading[i]:+.1f}" for i in marks))
        for i in big:
            print(f"  step {i + 1:4d}: off {err[i]:+.2f} deg (turn {turn_t[i]:+.1f}, "
                  f"wheels off {odo_err[i]:+.2f})")


if __name__ == "__main__":
    main()
