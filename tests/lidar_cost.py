"""What one scan of a real log costs, in CPU, and a digest of the whole run (``python
tests/lidar_cost.py LOG... [--profile lidar|lidar-slam] [--steps N]``): each CARMEN log is run
the way ``wiremap bench lidar`` runs it (seed 1, 10 particles, range cap 20 m, merge threshold
0.2 m, the profile's settings), and one line per log gives the CPU milliseconds per scan
(``time.process_time``) of what the bench's ``ms_per_scan`` counts -- the scans' extraction
(split-and-merge, and for ``lidar-slam`` the lidar SLAM over the log) and the filter's steps --
then two digests: of the filter's inputs (corner scans, raw points, odometry) and of the run
(every step's pose, best particle and mapping verdict, every particle's content, the weights).

A development measurement (figures in ``docs/experiments.md``), not one of ``wiremap bench``'s
benchmarks: on a shared machine CPU time is steadier than the bench's wall clock. Equal digests
in two checkouts mean the same run bit for bit. To compare two checkouts, run this file in each
(``PYTHONPATH=CHECKOUT python tests/lidar_cost.py ...``; it uses nothing newer than issue 17's
lidar-speed work started from).
"""

from __future__ import annotations

import argparse
import hashlib
import time

import numpy as np


def main() -> None:
    from agents import mapping_run as mr
    from agents.bench import lidar as bl
    from agents.files.carmen import read_carmen_log, scan_truth
    from mapping.config import with_overrides
    from mapping.filter import WireframeFilter

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", nargs="+", metavar="LOG")
    ap.add_argument("--profile", default="lidar", choices=("lidar", "lidar-slam", "none"))
    ap.add_argument("--steps", type=int, default=None, help="only the first N scans")
    args = ap.parse_args()
    settings = bl.settings_for(args.profile, [])
    for path in args.logs:
        log = read_carmen_log(path)
        truth = scan_truth(log)
        if truth is None:
            raise SystemExit(f"{path}: no truth beside it")
        scans = log.scans[: args.steps] if args.steps else log.scans
        truth = truth[: len(scans)]
        cap = min(float(scans[0].max_range), 20.0)
        c0 = time.process_time()
        fo, extract, frontend = mr.split_profile(dict(settings))
        inputs = list(mr.carmen_inputs(scans, max_range=cap, truth=truth, extract=extract,
                                       frontend=frontend))
        c1 = time.process_time()
        cfg = with_overrides(mr.filter_config_for(10, 0.2, cap, fov=mr.scan_fov(scans[0].angles)), fo)
        filt = WireframeFilter(cfg, mr.seeds_for(1)["filter"], initial_pose=truth[0])
        given = hashlib.blake2b(digest_size=8)
        for inp in inputs:
            given.update(inp.scan.content_digest())
            given.update(np.asarray(inp.points).tobytes())
            given.update(repr((inp.odometry.x, inp.odometry.y, inp.odometry.theta)).encode())
        c2 = time.process_time()
        run = hashlib.blake2b(digest_size=8)
        for inp in inputs:
            info = filt.step(inp.odometry, inp.scan, points=inp.points)
            p = filt.pose
            run.update(repr((p.x, p.y, p.theta, info.best, info.mapped)).encode())
            for q in filt.particles:
                run.update(q.content_digest())
            run.update(filt.weights.tobytes())
        c3 = time.process_time()
        n = max(1, len(inputs))
        print(f"{bl.log_name(path):14s} {args.profile:10s} scans {len(inputs):4d}"
              f"  extract {1e3 * (c1 - c0) / n:6.2f}  steps {1e3 * (c3 - c2) / n:6.2f}"
              f"  total {1e3 * ((c1 - c0) + (c3 - c2)) / n:6.2f} ms/scan CPU"
              f"  inputs {given.hexdigest()}  run {run.hexdigest()}", flush=True)


if __name__ == "__main__":
    main()
