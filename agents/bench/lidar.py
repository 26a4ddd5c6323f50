"""``wiremap bench lidar``: the mapper on real CARMEN lidar logs, scored against their truth.

For each log (``LOG ...``, or every ``*.log`` / ``*.log.gz`` in ``--data DIR``) the laser scans
are read as they are (:func:`agents.files.carmen.read_carmen_log`, unreadable lines skipped and
counted), a dense log's thinned by the motion filter (:func:`agents.mapping_run.motion_filtered`,
``scans_left_out``; none of the shared logs is dense; ``scans`` counts the scans mapped and
scored), turned into corner scans once (split-and-merge, :func:`agents.mapping_run.carmen_inputs`)
and fed to the particle filter (and with ``--baseline`` to the one-particle mapper on the same
scans). The filter starts at the true first pose. The truth is the log's ``NAME.truth.tsv`` or
its ``TRUEPOS`` track (:func:`agents.files.carmen.scan_truth`); a log without either is an error.

Scores (:mod:`mapping.lidar_metrics`), per log and method:

* ``ate_rmse_m``, ``ate_max_m`` -- position error of the estimated sensor pose, no alignment;
* ``rpe_1m_m`` -- mean relative error over pose pairs 1 m apart along the true path;
* ``map_precision`` -- share of points every 5 cm along the map's walls within 0.2 m of a real
  scan endpoint placed at the true pose; ``map_coverage`` -- share of those endpoints within
  0.2 m of a map wall. Endpoints are the returns within the mapper's range cap
  (``max_range_m``), the part of the scan the mapper is given; ``map_precision_aligned`` --
  the precision after one rigid alignment of the map to the endpoints, with the alignment's
  size (``alignment_m``, ``alignment_deg``): a map turned about its start apart from a bent one;
* ``best_map_bytes`` -- the best particle's map as one wire message (:func:`wire_codec.encode`,
  a ``ROBOT_MAP`` at the robot agent's 0.05 m resolution); ``particle_bytes`` --
  :func:`mapping.filter.particle_bytes` of the whole particle set (paper Sec. IV-G);
* ``time_s`` -- wall-clock seconds of split-and-merge plus the filter's steps; ``ms_per_scan``;
* ``odometry_ate_rmse_m``, ``odometry_ate_max_m``, ``odometry_rpe_1m_m`` -- the log's own
  (drifting) odometry, beside them.

Real-log settings, passed from here and never changed in the mapper: the range cap (default
20 m, as ``wiremap map``), the merge threshold (0.2 m), the field of view from the log's beams,
and a real-lidar profile (:data:`agents.mapping_run.LIDAR_PROFILES`: ``lidar-slam``, the default,
lidar SLAM under the filter; ``lidar``, the filter's corner ICP alone; ``none`` for the
simulator's defaults) with any ``--set KEY=VALUE``
on top (dotted keys: ``extract.*``, ``frontend.*``, else :class:`mapping.filter.FilterConfig`'s).
The settings applied are in the JSON as ``"settings"``.

Output: an aligned table on stdout, a PNG per log in ``--out`` (the map over the endpoints, with
the true and estimated paths, a legend and a scale bar), and with ``--json`` one last line::

    {"logs": {NAME: {"scans", "ate_rmse_m", ..., ["baseline": {...}], ["truth_poses": {...}]}},
     "median": {...}, "profile": "lidar-slam", "settings": {KEY: VALUE, ...}}

where ``median`` holds the medians over logs of every numeric key (and of the extra runs' under
their keys). ``--truth-poses`` maps each log once more with the truth's increments in place of
the SLAM's (:func:`truth_fed`): its precision and coverage are the mapper's own (extraction,
filter), so the gap to the filter's row is what the pose costs the map.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.argtypes import non_negative_int, positive_int
from agents.bench.common import Progress, aligned_rows, fmt_cell
from agents.errors import UserError
from agents.mapping_run import LIDAR_PROFILES

HELP = "the mapper on real CARMEN lidar logs against their truth (ATE, map precision, bytes)"

ODOMETRY_KEYS = ("odometry_ate_rmse_m", "odometry_ate_max_m", "odometry_rpe_1m_m")
INT_KEYS = ("scans", "best_map_bytes", "particle_bytes", "vertices", "edges", "skipped_lines",
            "particles", "seed", "odometry_noise_pairs")
WIRE_RESOLUTION = 0.05  # the robot agent's map resolution (agents.fleet.robot.DEFAULT_RESOLUTION)
TOL = 0.2  # metres, precision and coverage
SPACING = 0.05  # metres between wall samples
RPE_DISTANCE = 1.0
#: The runs beside the filter's, by their key in a log's result and their name in the table:
#: ``--baseline`` (one particle) and ``--truth-poses`` (the filter at the truth's poses).
EXTRA_RUNS = {"baseline": "baseline", "truth_poses": "truth-poses"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_log_arguments(parser)
    parser.add_argument("--seed", type=non_negative_int, default=1,
                        help="random seed of the filter (default 1)")
    parser.add_argument("--particles", type=int, default=10, help="particles (default 10)")
    parser.add_argument("--steps", type=positive_int, default=None, metavar="N",
                        help="only the first N scans of each log (before a dense log is thinned)")
    parser.add_argument("--max-range", type=float, default=20.0, metavar="M",
                        help="range cap given to the mapper, metres (default 20, as wiremap map)")
    parser.add_argument("--merge-threshold", type=float, default=0.2, metavar="M",
                        help="merge threshold, metres (default 0.2)")
    parser.add_argument("--baseline", action="store_true", help="also run the one-particle mapper")
    parser.add_argument("--truth-poses", action="store_true",
                        help="also map at the truth's poses (the same filter fed the truth's increments): "
                             "how much of the map's imprecision is the pose's")
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")
    parser.add_argument("--out", default="out/bench-lidar", metavar="DIR", help="where the PNGs go")
    parser.add_argument("--jobs", type=int, default=1, metavar="N",
                        help="run N logs at once in separate processes (default 1; they share the cores)")
    parser.add_argument("--profile", choices=(*LIDAR_PROFILES, "none"), default="lidar-slam",
                        help="real-lidar settings (agents.mapping_run.LIDAR_PROFILES): lidar-slam "
                             "(lidar SLAM under the filter; default), lidar (the filter's own corner "
                             "ICP holds the pose) or none")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                        help="override one setting (dotted key, e.g. odometry.rot_per_m=0.05); repeatable")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def settings_for(profile: str, sets: list[str]) -> dict[str, Any]:
    """The profile's overrides with ``--set KEY=VALUE`` ones on top, checked.

    Raises
    ------
    UserError
        A ``--set`` without ``=``, or a key or value the configuration rejects.
    """
    from agents import mapping_run as mr
    from mapping.config import ConfigError, with_overrides
    from mapping.filter import FilterConfig

    out: dict[str, Any] = mr.lidar_profile(profile) if profile != "none" else {}
    for item in sets:
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise UserError(f"--set {item!r}: expected KEY=VALUE")
        out[key.strip()] = value.strip()
    try:
        fo, extract, frontend = mr.split_profile(out)
        fcfg = with_overrides(FilterConfig(), fo)
    except (ConfigError, ValueError) as exc:
        raise UserError(f"--set: {exc}") from None
    for item in sets:  # each --set value as the configuration took it (a number, not its text)
        key = item.partition("=")[0].strip()
        head, _, rest = key.partition(".")
        obj, path = {"extract": (extract, rest), "frontend": (frontend, rest),
                     "slam": (frontend, key)}.get(head, (fcfg, key))
        out[key] = functools.reduce(getattr, path.split("."), obj)
    return out


def log_name(path: str | Path) -> str:
    """``freiburg-101`` for ``.../freiburg-101.log.gz``."""
    name = Path(path).name
    for suffix in (".gz", ".log"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
    return name


def add_log_arguments(parser: argparse.ArgumentParser, what: str = "CARMEN logs (.log or .log.gz)") -> None:
    """The logs a real-log benchmark runs: ``LOG ...`` or ``--data DIR`` (:func:`find_logs`)."""
    parser.add_argument("logs", nargs="*", metavar="LOG", help=what)
    parser.add_argument("--data", metavar="DIR", help="take every *.log and *.log.gz in DIR")


def find_logs(logs: list[str], data: str | None) -> list[Path]:
    """The logs to run: those named, else every ``*.log`` / ``*.log.gz`` in ``data``.

    Raises
    ------
    UserError
        Without logs and without ``data``, for a named log that is not a file, for a missing
        folder or one without logs, and for two logs of the same name.
    """
    if logs:
        paths = [Path(p) for p in logs]
        missing = next((p for p in paths if not p.is_file()), None)
        if missing is not None:
            raise UserError(f"{missing}: no such file")
    elif data is not None:
        d = Path(data)
        if not d.is_dir():
            raise UserError(f"--data {data}: no such folder")
        paths = sorted(
            p for p in d.iterdir() if p.is_file() and (p.name.endswith(".log") or p.name.endswith(".log.gz"))
        )
        if not paths:
            raise UserError(f"--data {data}: no *.log or *.log.gz files there")
    else:
        raise UserError("no logs: pass LOG files or --data DIR (e.g. --data ../shared/data/carmen)")
    names = [log_name(p) for p in paths]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise UserError(f"two logs are named {dup}")
    return paths


def _check(args: argparse.Namespace) -> None:
    if args.particles < 1:
        raise UserError(f"--particles must be >= 1, got {args.particles}")
    if args.steps is not None and args.steps < 1:
        raise UserError(f"--steps must be >= 1, got {args.steps}")
    if args.jobs < 1:
        raise UserError(f"--jobs must be >= 1, got {args.jobs}")
    for flag, v in (("--max-range", args.max_range), ("--merge-threshold", args.merge_threshold)):
        if not (math.isfinite(v) and v > 0):
            raise UserError(f"{flag} must be a positive number of metres, got {v}")


def wire_bytes(wf: Any, pose: Any) -> int:
    """Bytes of ``wf`` as one ``ROBOT_MAP`` wire message (:func:`wire_codec.encode`)."""
    from mapping.se2 import Pose
    from wire_codec import encode
    from wire_codec.message import MapMessage, MessageKind

    if wf.n_edges and wf.sources.any():
        wf = wf.replace(sources=np.zeros(wf.n_edges, dtype=np.uint64))
    msg = MapMessage(
        kind=MessageKind.ROBOT_MAP, sender="r1", seq=0, stamp_ns=0, pose=pose, frame="odom/r1",
        origin=Pose(), resolution=WIRE_RESOLUTION, wireframe=wf,
    )
    return len(encode(msg))


def pose_array(ps: list[Any]) -> np.ndarray:
    """Poses (objects with x, y, theta) as an (n, 3) array."""
    return np.array([[p.x, p.y, p.theta] for p in ps], dtype=np.float64).reshape(-1, 3)


def run_log(
    path: str, *, seed: int, particles: int, steps: int | None, max_range: float, thr: float,
    baseline: bool, out: str, progress: bool = False, settings: dict[str, Any] | None = None,
    truth_poses: bool = False,
) -> dict[str, Any]:
    """One log: read it, map it (and the baseline, and the map at the truth's poses, on the same
    scans), score, write its PNGs. Every run's ``time_s`` counts the log's extraction and SLAM.
    Returns the log's result object (see the module notes). Runs in a worker process too."""
    from agents import mapping_run as mr
    from agents.bench.lidar_png import lidar_png
    from agents.files.carmen import read_carmen_log, scan_truth
    from agents.files.io import write_atomic
    from mapping.config import with_overrides
    from mapping.filter import WireframeFilter, particle_bytes
    from mapping.lidar_metrics import ate, rpe, scan_endpoints, score_run

    name = log_name(path)
    show = Progress(progress, live=True)
    log = read_carmen_log(path)
    if not log.scans:
        raise UserError(f"{path}: no laser scans in the log")
    truth = scan_truth(log)
    if truth is None:
        raise UserError(f"{path}: no truth (no TRUEPOS lines and no {log_name(path)}.truth.tsv beside it)")
    scans = log.scans[:steps] if steps is not None else log.scans
    truth = truth[: len(scans)]
    cap = min(float(scans[0].max_range), max_range)
    fov = mr.scan_fov(scans[0].angles)  # the scanner's, before a de-skew bends the first scan
    filter_overrides, extract_cfg, frontend_cfg = mr.split_profile(dict(settings or {}))
    t0 = time.perf_counter()
    sweep = mr.judged_sweep(scans, frontend_cfg)  # the order of the beams, for the de-skew and the report
    scans, kept_truth, left_out = mr.motion_filtered(scans, truth, frontend_cfg, sweep)  # de-skewed, thinned
    assert kept_truth is not None
    truth = kept_truth
    cal = mr.calibrate_log(scans, frontend_cfg)
    noise = [cal.noise]  # the online SLAM's last measure of the wheels (mapping.lidar_frontend.OnlineSlam)
    inputs = list(mr.carmen_inputs(scans, max_range=cap, truth=truth, extract=extract_cfg,
                                   frontend=frontend_cfg, calibration=cal, on_noise=noise.append))
    extract_s = time.perf_counter() - t0
    true_xyt = pose_array(truth)
    odom_xyt = pose_array([s.odom for s in scans])
    endpoints = scan_endpoints(true_xyt, [s.ranges for s in scans], [s.angles for s in scans], max_range=cap)

    def one(method: str, p: int, feed: list[Any] = inputs) -> tuple[dict[str, Any], Any, np.ndarray]:
        cfg = with_overrides(mr.filter_config_for(p, thr, cap, fov=fov), filter_overrides)
        filt = WireframeFilter(cfg, mr.seeds_for(seed)["filter"], initial_pose=truth[0])
        busy = 0.0
        est = []
        for st in mr.run_filter(feed, filt, len(feed)):
            busy += st.step_s
            est.append(st.pose)
            show.update(f"{name} {method}: scan {st.index + 1}/{len(inputs)}, "
                        f"{filt.best.n_edges} walls, {(st.index + 1) / busy if busy else 0:.1f} scans/s")
        best = filt.best
        est_xyt = pose_array(est)
        secs = extract_s + busy
        row = {
            "scans": len(inputs),
            **score_run(est_xyt, true_xyt, best, endpoints, TOL, SPACING, RPE_DISTANCE),
            "best_map_bytes": wire_bytes(best, filt.pose),
            "particle_bytes": particle_bytes(filt.particles),
            "vertices": best.n_vertices,
            "edges": best.n_edges,
            "time_s": secs,
            "ms_per_scan": 1000.0 * secs / len(inputs),
        }
        show.line(f"{name} {method}: ATE {row['ate_rmse_m']:.3f} m (max {row['ate_max_m']:.2f}), "
                  f"precision {row['map_precision']:.3f}, coverage {row['map_coverage']:.3f}, "
                  f"{row['ms_per_scan']:.0f} ms/scan")
        return row, best, est_xyt

    result, best, est_xyt = one("filter", particles)
    o_rmse, o_max = ate(odom_xyt, true_xyt)
    result.update({
        "odometry_ate_rmse_m": o_rmse,
        "odometry_ate_max_m": o_max,
        "odometry_rpe_1m_m": rpe(odom_xyt, true_xyt, RPE_DISTANCE),
        "skipped_lines": len(log.issues),
        "scans_left_out": left_out,
        "particles": particles,
        "seed": seed,
        "max_range_m": cap,
        **mr.yaw_report(cal),
        **mr.odometry_report(noise[-1], frontend_cfg.slam),
        **mr.sweep_report(sweep),
    })
    title = f"{name}: ate {result['ate_rmse_m']:.2f} m, precision {result['map_precision']:.2f}, seed {seed}"
    write_atomic(Path(out) / f"{name}.png",
                 lidar_png(best, endpoints, true_xyt[:, :2], est_xyt[:, :2], title=title))
    if baseline:
        brow, bbest, best_xyt = one("baseline", 1)
        result["baseline"] = brow
        write_atomic(Path(out) / f"{name}-baseline.png",
                     lidar_png(bbest, endpoints, true_xyt[:, :2], best_xyt[:, :2], title=f"{name}: baseline"))
    if truth_poses:
        trow, tbest, _ = one("truth-poses", particles, truth_fed(inputs, truth))
        result["truth_poses"] = trow
        title = f"{name} at the truth's poses: precision {trow['map_precision']:.2f}, seed {seed}"
        write_atomic(Path(out) / f"{name}-truth-poses.png",
                     lidar_png(tbest, endpoints, true_xyt[:, :2], title=title))
    return _rounded(result)


def truth_fed(inputs: list[Any], truth: list[Any]) -> list[Any]:
    """``inputs`` (:class:`agents.mapping_run.ScanInput`) with each scan's motion taken from the
    truth (``truth[k - 1].between(truth[k])``, the identity for the first) instead of the SLAM or
    the wheels: the mapper's own share of a map's errors, without the pose's."""
    import dataclasses

    from mapping.se2 import increments

    return [dataclasses.replace(inp, odometry=odo) for inp, odo in zip(inputs, increments(truth))]


def _rounded(d: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out[k] = _rounded(v)
        elif isinstance(v, bool) or v is None:
            out[k] = v
        elif k in INT_KEYS or isinstance(v, int):
            out[k] = int(v)
        else:
            f = float(v)
            out[k] = round(f, 6) if math.isfinite(f) else None
    return out


def median(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Median over logs of every numeric key (None when no log has a finite value; flags and
    nested runs left out)."""
    keys = [k for k in rows[0] if not isinstance(rows[0][k], (dict, bool))] if rows else []
    out: dict[str, Any] = {}
    for k in keys:
        vals = np.array([r[k] for r in rows if r.get(k) is not None], dtype=np.float64)
        vals = vals[np.isfinite(vals)]
        m = float(np.median(vals)) if len(vals) else math.nan
        out[k] = None if not math.isfinite(m) else (round(m) if k in INT_KEYS else round(m, 6))
    return out


def format_table(logs: dict[str, dict[str, Any]], med: dict[str, Any]) -> str:
    """One line per log and method (filter, baseline, truth-poses, odometry), then the medians
    (``med`` holds the extra runs' medians under their keys, as the JSON does)."""
    head = ["log", "method", "scans", "ate_m", "ate_max_m", "rpe_1m_m", "precision", "coverage",
            "aligned", "map_B", "particle_B", "time_s", "ms/scan"]
    lines = [head]

    def add(name: str, method: str, r: dict[str, Any]) -> None:
        lines.append([
            name, method, fmt_cell(r.get("scans"), "{}"), fmt_cell(r.get("ate_rmse_m"), "{:.3f}"),
            fmt_cell(r.get("ate_max_m"), "{:.3f}"), fmt_cell(r.get("rpe_1m_m"), "{:.3f}"),
            fmt_cell(r.get("map_precision"), "{:.3f}"), fmt_cell(r.get("map_coverage"), "{:.3f}"),
            fmt_cell(r.get("map_precision_aligned"), "{:.3f}"), fmt_cell(r.get("best_map_bytes"), "{}"),
            fmt_cell(r.get("particle_bytes"), "{}"),
            fmt_cell(r.get("time_s"), "{:.1f}"), fmt_cell(r.get("ms_per_scan"), "{:.0f}"),
        ])

    def odometry(name: str, r: dict[str, Any]) -> None:
        add(name, "odometry", {"scans": r.get("scans"), "ate_rmse_m": r.get("odometry_ate_rmse_m"),
                               "ate_max_m": r.get("odometry_ate_max_m"),
                               "rpe_1m_m": r.get("odometry_rpe_1m_m")})

    for name, r in logs.items():
        add(name, "filter", r)
        for key, method in EXTRA_RUNS.items():
            if key in r:
                add(name, method, r[key])
        odometry(name, r)
    add("median", "filter", med)
    for key, method in EXTRA_RUNS.items():
        if key in med:
            add("median", method, med[key])
    odometry("median", med)
    return aligned_rows(lines, left=2)



def run(args: argparse.Namespace) -> int:
    from concurrent.futures import ProcessPoolExecutor

    _check(args)
    paths = find_logs(list(args.logs), args.data)
    settings = settings_for(args.profile, list(args.sets))
    job = functools.partial(
        run_log, seed=args.seed, particles=args.particles, steps=args.steps, max_range=args.max_range,
        thr=args.merge_threshold, baseline=bool(args.baseline), out=str(args.out), settings=settings,
        truth_poses=bool(args.truth_poses),
    )
    results: dict[str, dict[str, Any]] = {}
    say = Progress(not args.quiet, live=False)
    t0 = time.perf_counter()
    if args.jobs == 1 or len(paths) == 1:
        for p in paths:
            results[log_name(p)] = job(str(p), progress=not args.quiet)
    else:
        with ProcessPoolExecutor(max_workers=min(args.jobs, len(paths))) as pool:
            futures = {log_name(p): pool.submit(job, str(p)) for p in paths}
            for name, fut in futures.items():
                results[name] = fut.result()
                r = results[name]
                say.line(f"{name}: ATE {r['ate_rmse_m']} m, precision {r['map_precision']}, "
                         f"{r['ms_per_scan']} ms/scan [{len(results)}/{len(paths)} logs, "
                         f"{time.perf_counter() - t0:.0f} s]")
    rows = list(results.values())
    med = median(rows)
    for key in EXTRA_RUNS:
        extra = [r[key] for r in rows if key in r]
        if extra:
            med[key] = median(extra)
    print(format_table(results, med))
    print(f"PNGs in {args.out}/")
    if args.json:
        print(json.dumps({"logs": results, "median": med, "profile": args.profile, "settings": settings}))
    return 0
