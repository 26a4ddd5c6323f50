"""A development measurement (not a test): a live robot's map after N passes of a log (as ``wiremap
bench live`` drives it, with the live robot's defaults) against the same filter inputs mapped again
at the online SLAM's *final* poses -- an oracle for walls that move with the pose graph.

``python -m tests.live_rebuild LOG PASSES`` (from the repository's folder)
"""

from __future__ import annotations

import sys
import time

from agents import mapping_run as mr
from agents.bench.lidar import pose_array
from agents.bench.live import shift
from agents.fleet.live_lidar import CALIBRATION_SCANS, live_filter
from mapping.lidar_metrics import map_precision, scan_endpoints
from mapping.se2 import Pose
from tests.live_ate import live_log


def main() -> None:
    path, passes = sys.argv[1], int(sys.argv[2])
    scans, truth, fo, extract, frontend = live_log(path, CALIBRATION_SCANS)
    filt, cap = live_filter(scans[0], 5, 0.2, 1, fo)  # the live robot's, at its defaults
    live = mr.LiveInputs(max_range=cap, extract=extract, frontend=frontend, min_travel=frontend.min_travel,
                         min_turn=frontend.min_turn)
    endpoints = scan_endpoints(pose_array(truth), [s.ranges for s in scans], [s.angles for s in scans],
                               max_range=cap)
    kept: list[mr.ScanInput] = []
    for _, ls in shift(scans, passes):
        for inp in live.add(ls):
            mr.feed(filt, inp)
            kept.append(inp)
    for inp in live.finish():
        mr.feed(filt, inp)
        kept.append(inp)
    origin = truth[0]
    p_live = map_precision(filt.best.transformed(origin), endpoints, 0.2)
    poses = [Pose(*map(float, p)) for p in live.slam.scan_poses()]  # the k-th scan mapped
    assert len(poses) == len(kept), (len(poses), len(kept))
    t0 = time.process_time()
    again = live_filter(scans[0], 5, 0.2, 1, fo)[0]
    prev: Pose | None = None
    for inp, p in zip(kept, poses, strict=True):
        again.step(Pose.identity() if prev is None else prev.between(p), inp.scan, points=inp.points)
        prev = p
    dt = time.process_time() - t0
    p_again = map_precision(again.best.transformed(origin), endpoints, 0.2)
    print(f"{path.split('/')[-1]} {passes} passes, {len(kept)} scans: live map precision {p_live:.3f}, "
          f"mapped again at the final poses {p_again:.3f} ({dt:.1f} s CPU, "
          f"{1000 * dt / len(kept):.1f} ms a scan)")


if __name__ == "__main__":
    main()
