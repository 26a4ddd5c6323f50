"""``wiremap bench sensor``: how good are the simulated sensors along a world's route?

Two figures, each over every scan of the world's planned route (true poses, seeded):

* **corner sensor label accuracy**: the share of true corners (the noise-free view of the truth,
  :meth:`CornerSensor.true_scan`) whose nearest measured corner within ``--tol`` carries the same
  label, and the share of true corners detected at all (``p_fn`` drops walls, and their corners
  with them);
* **split-and-merge corner error**: ray-cast noisy lidar ranges, extract corners with
  :func:`mapping.extract.extract_corners`, and measure the distance from each true NOMINAL corner
  in the lidar's view to the nearest extracted corner (median and p95 over corners found within
  ``--tol``), plus the share detected and the label agreement.

Prints a table and, with ``--json``, one JSON object as the last line:
``{"tol_m", "seed", "worlds": {NAME: {"scans", "label_accuracy", "corner_detection",
"lidar_scans", "lidar_nominal_error_m_p50", "lidar_nominal_error_m_p95", "lidar_detection",
"lidar_label_accuracy"}}}``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np
from scipy.spatial import cKDTree

from agents.sim.lidar import LidarConfig, raycast
from agents.sim.motion import drive
from agents.sim.route import plan_route
from agents.sim.sensor import CornerSensor, CornerSensorConfig, LabelStats, label_stats
from agents.sim.world import load_world
from mapping.extract import extract_corners
from mapping.wireframe import Label

HELP = "label accuracy of the corner sensor and corner error of split-and-merge on lidar"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--worlds", default="paper-small,museum",
                        help="comma-separated worlds (default paper-small,museum)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--tol", type=float, default=0.1, help="matching tolerance in metres (default 0.1)")
    parser.add_argument("--lidar-every", type=int, default=5,
                        help="use every k-th pose for lidar (default 5)")
    parser.add_argument("--json", action="store_true", help="print the JSON object as the last line")


def _world_figures(name: str, seed: int, tol: float, lidar_every: int) -> dict[str, float]:
    world = load_world(name)
    rng = np.random.default_rng(seed)
    steps = drive(plan_route(world, rng), rng=rng)
    sensor = CornerSensor(world.truth, CornerSensorConfig())
    total = LabelStats(0, 0, 0)
    for st in steps:
        total = total + label_stats(sensor.scan(st.true_pose, rng), sensor.true_scan(st.true_pose), tol)

    lidar = LidarConfig(beams=720, fov=2 * math.pi, max_range=sensor.config.max_range)
    lidar_view = CornerSensor(world.truth,
                              CornerSensorConfig(max_range=lidar.max_range, sigma=0.0, p_fp=0.0, p_fn=0.0))
    segs = world.truth.segments()
    errors: list[float] = []
    n_true = n_same = n_scans = 0
    for st in steps[::lidar_every]:
        ranges = raycast(segs, st.true_pose, lidar, rng)
        scan = extract_corners(ranges, lidar.angles(), lidar.max_range)
        truth = lidar_view.true_scan(st.true_pose)
        nominal = truth.points[truth.labels == Label.NOMINAL]
        n_scans += 1
        n_true += len(nominal)
        if len(nominal) == 0 or scan.n_vertices == 0:
            continue
        d, j = cKDTree(scan.points).query(nominal)
        hit = d <= tol
        errors.extend(d[hit].tolist())
        n_same += int(np.sum(scan.labels[j[hit]] == Label.NOMINAL))
    err = np.asarray(errors)
    return {
        "scans": len(steps),
        "label_accuracy": round(total.accuracy, 5),
        "corner_detection": round(total.detection, 5),
        "lidar_scans": n_scans,
        "lidar_nominal_error_m_p50": round(float(np.median(err)), 5) if len(err) else math.nan,
        "lidar_nominal_error_m_p95": round(float(np.quantile(err, 0.95)), 5) if len(err) else math.nan,
        "lidar_detection": round(len(err) / n_true, 5) if n_true else math.nan,
        "lidar_label_accuracy": round(n_same / len(err), 5) if len(err) else math.nan,
    }


def run(args: argparse.Namespace) -> int:
    names = [w for w in args.worlds.split(",") if w]
    out: dict[str, dict[str, float]] = {}
    for name in names:
        print(f"[bench sensor] {name} ...", file=sys.stderr, flush=True)
        out[name] = _world_figures(name, args.seed, args.tol, max(1, args.lidar_every))
    keys = list(next(iter(out.values())).keys()) if out else []
    width = max((len(k) for k in keys), default=0) + 2
    print(f"{'':<{width}}" + "".join(f"{name:>14}" for name in out))
    for k in keys:
        print(f"{k:<{width}}" + "".join(f"{out[name][k]:>14}" for name in out))
    if args.json:
        print(json.dumps({"tol_m": args.tol, "seed": args.seed, "worlds": out}))
    return 0
