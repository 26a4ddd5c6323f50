"""Where the lidar SLAM's heading goes wrong on a real log (``python tests/slam_heading.py
LOG... [--oracle] [--scans I0:I1] [--set KEY=VALUE]``).

By default: the ``lidar-slam`` profile's SLAM over each CARMEN log from the true first pose (as
``wiremap bench lidar`` runs it), then, against the truth beside the log, its ATE, the heading
error every tenth of the log, and each step's turn error (the SLAM's turn between two scans less
the truth's): its RMS, its sum, and the steps off by more than 0.7 degree with the truth's turn
and the wheels' error on the same step. Then the same measure on the SLAM's ``online`` poses and
the share of the step errors that follows the wheels' (``leak``: the least-squares factor of
the wheels' step error in the SLAM's).

``--scans I0:I1``: the SLAM over that stretch alone from the truth's pose at ``I0`` (what a
robot of ``wiremap run --carmen`` maps), beside the whole log's SLAM placed at the same pose.

``--oracle``: no SLAM; each scan matched once (the SLAM's local match, its settings and heading
prior) against a submap of the ``local_scans`` scans before it placed at the truth's poses, from
the truth's previous pose composed with the wheels' step: the match's heading error when the
map it matches is right, with the prior and without.

A development measurement (figures in ``docs/experiments.md``), not a benchmark.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def _step_errors(est: np.ndarray, tr: np.ndarray) -> np.ndarray:
    return _wrap_deg(_wrap_deg(np.degrees(np.diff(est[:, 2]))) - _wrap_deg(np.degrees(np.diff(tr[:, 2]))))


def _whole(path: str, settings: dict[str, Any]) -> None:
    from agents.bench.lidar import pose_array
    from agents.bench.slam import slam_over_log
    from mapping.lidar_metrics import ate

    run = slam_over_log(path, settings)
    slam = run.slam
    est, tr = slam.scan_poses(), pose_array(run.truth)
    odo = pose_array([s.odom for s in run.scans])
    heading = _wrap_deg(np.degrees(est[:, 2] - tr[:, 2]))
    turn_t = _wrap_deg(np.degrees(np.diff(tr[:, 2])))
    err, odo_err = _step_errors(est, tr), _step_errors(odo, tr)
    big = np.flatnonzero(np.abs(err) > 0.7)
    print(f"{path}: ATE {ate(est, tr)[0]:.3f} m, {len(slam.loops)} loops; step turn error RMS "
          f"{np.sqrt(np.mean(err ** 2)):.2f} deg, sum {err.sum():+.2f} deg, {len(big)} of {len(err)} "
          "steps off by > 0.7 deg")
    for name, poses in (("online", np.asarray(slam.online)), ("final", est)):
        e = _step_errors(poses, tr)
        leak = float(np.dot(e, odo_err) / np.dot(odo_err, odo_err))
        print(f"  {name}: step RMS {np.sqrt(np.mean(e ** 2)):.3f} deg, leak {leak:.3f}, without it "
              f"{np.sqrt(np.mean((e - leak * odo_err) ** 2)):.3f} (wheels' step RMS "
              f"{np.sqrt(np.mean(odo_err ** 2)):.2f})")
    every = max(1, len(est) // 10)
    marks = range(0, len(est), every)
    print("  heading error by scan: " + ", ".join(f"{i} {heading[i]:+.1f}" for i in marks))
    for i in big:
        print(f"  step {i + 1:4d}: off {err[i]:+.2f} deg (turn {turn_t[i]:+.1f}, "
              f"wheels off {odo_err[i]:+.2f})")


def _stretch(path: str, settings: dict[str, Any], i0: int, i1: int) -> None:
    from agents import mapping_run as mr
    from agents.bench.lidar import pose_array
    from agents.bench.slam import slam_over_log
    from mapping.lidar_frontend import run_slam
    from mapping.lidar_metrics import ate
    from mapping.se2 import Pose

    run = slam_over_log(path, settings)
    tr = pose_array(run.truth)[i0:i1]
    part = run.scans[i0:i1]

    def placed(poses: Any, k0: int) -> np.ndarray:
        ps = [Pose(*map(float, p)) for p in poses]
        to = run.truth[i0].compose(ps[k0].inverse())
        return np.array([to.compose(p).as_tuple() for p in ps])

    _, _, fcfg = mr.split_profile(settings)
    cal = mr.calibrate_log(part, fcfg)
    alone = run_slam(cal.points, mr.wheel_increments(part), fcfg.slam, noise=cal.noise)
    whole = placed(run.slam.scan_poses(), i0)[i0:i1]
    for name, est, loops in (("whole log's SLAM", whole, len(run.slam.loops)),
                             ("whole log's SLAM online", placed(run.slam.online, i0)[i0:i1], None),
                             ("the stretch's own SLAM", placed(alone.scan_poses(), 0), len(alone.loops))):
        h = _wrap_deg(np.degrees(est[:, 2] - tr[:, 2]))
        every = max(1, len(est) // 8)
        print(f"{path} {i0}:{i1} {name}: ATE {ate(est, tr)[0]:.3f} m, max {ate(est, tr)[1]:.3f}"
              + (f", {loops} loops" if loops is not None else "")
              + "; heading error " + ", ".join(f"{i0 + i} {h[i]:+.1f}" for i in range(0, len(est), every)))


def _oracle(path: str, settings: dict[str, Any]) -> None:
    from agents import mapping_run as mr
    from agents.bench.lidar import pose_array
    from agents.files.carmen import read_carmen_log, scan_truth
    from mapping.lidar_frontend import calibrated_slam
    from mapping.lidar_slam import Submap, _apply, _compose, _rot, match_scan, scan_normals

    log = read_carmen_log(path)
    truth = scan_truth(log)
    if truth is None:
        raise SystemExit(f"{path}: no truth")
    tr = pose_array(truth)
    _, _, fcfg = mr.split_profile(settings)
    cal = mr.calibrate_log(log.scans, fcfg)
    cfg = calibrated_slam(fcfg.slam, cal.noise) if cal.noise is not None else fcfg.slam
    odo = [np.array(o.as_tuple()) for o in mr.wheel_increments(log.scans)]
    pts = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in cal.points]
    nrm = [scan_normals(p, cfg.normal_gap) for p in pts]
    errs: dict[str, list[float]] = {"with the prior": [], "without": []}
    for k in range(cfg.local_scans, len(pts)):
        sub = Submap.build([(_apply(tr[i], pts[i]), nrm[i] @ _rot(tr[i][2]).T)
                            for i in range(k - cfg.local_scans, k)], cfg.voxel)
        guess = _compose(tr[k - 1], odo[k])
        d = math.hypot(odo[k][0], odo[k][1])
        sxy = max(cfg.odo_floor_xy, cfg.odo_trans_per_m * d)
        sth = max(cfg.odo_floor_theta, cfg.odo_rot_per_m * d + cfg.odo_rot_per_rad * abs(odo[k][2]))
        prior = np.diag([1 / sxy**2, 1 / sxy**2, 1 / sth**2])
        for name, p in (("with the prior", prior), ("without", None)):
            m = match_scan(pts[k], sub, guess, cfg, prior_information=p)
            if m.matched >= 10:
                errs[name].append(math.degrees(math.remainder(m.pose[2] - tr[k][2], math.tau)))
    if not errs["without"]:
        print(f"{path}: no scan matched against the truth's submap")
        return
    out = []
    for name, e in errs.items():
        a = np.array(e)
        out.append(f"{name}: mean {a.mean():+.3f} RMS {np.sqrt(np.mean(a ** 2)):.3f} "
                   f"p90 |e| {np.quantile(np.abs(a), 0.9):.3f} deg")
    print(f"{path}: {len(errs['without'])} scans matched against the truth's submap; " + "; ".join(out))


def main() -> None:
    from agents.bench.lidar import settings_for

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", nargs="+", metavar="LOG")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets")
    ap.add_argument("--oracle", action="store_true")
    ap.add_argument("--scans", metavar="I0:I1")
    args = ap.parse_args()
    if args.oracle and args.scans:
        ap.error("--oracle matches every scan of the log: no --scans")
    settings = settings_for("lidar-slam", list(args.sets))
    for path in args.logs:
        if args.oracle:
            _oracle(path, settings)
        elif args.scans:
            i0, i1 = (int(v) for v in args.scans.split(":"))
            _stretch(path, settings, i0, i1)
        else:
            _whole(path, settings)


if __name__ == "__main__":
    main()
