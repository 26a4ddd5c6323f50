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
    from agents.bench.lidar import pose_array, settings_for
    from agents.bench.slam import slam_over_log
    from mapping.lidar_metrics import ate

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", nargs="+", metavar="LOG")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets")
    args = ap.parse_args()
    settings = settings_for("lidar-slam", list(args.sets))
    for path in args.logs:
        run = slam_over_log(path, settings)
        slam = run.slam
        est, tr = np.asarray(slam.poses), pose_array(run.truth)
        odo = pose_array([s.odom for s in run.scans])
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
