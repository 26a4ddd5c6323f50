"""``wiremap bench live``: a real robot's live mapper over a long shift, on real CARMEN logs.

A robot maps for hours; a log lasts minutes. This bench drives each log forward, then back
along the same scans, ``--passes`` times -- a robot on duty sees its building again and again --
through what ``wiremap robot --scan-key`` runs on each scan it takes: the live input stage
(:class:`agents.mapping_run.LiveInputs`: the motion filter, the calibrations on the first
``--calibration-scans``, the online SLAM of the ``lidar-slam-online`` profile) and the filter,
with the live robot's settings (:func:`agents.fleet.live_lidar.live_profile`, ``--particles``
and ``--threshold`` as ``wiremap robot``'s defaults). One log runs in one process of its own, so
its memory is its own.

What it answers: does a scan cost the same in the tenth pass as in the first (the online SLAM's
graph grows with every scan, and every loop it closes was a Gauss-Newton over all of it), does
the memory stay within what the scans themselves need, and does the map stay right.

Per log and per pass (JSON ``by_pass``): scans mapped, CPU ms per scan mapped of the input stage
(extraction and SLAM) and of the filter, loops closed and how many of them were *settled*
(:attr:`mapping.lidar_slam.SlamConfig.loop_settled_xy`: no re-optimisation), the SLAM's graph
at the pass's end (``graph``: its nodes) and the scans it posed on old nodes instead
(``revisits``: :attr:`mapping.lidar_slam.SlamConfig.revisit_xy`), the nodes its online
refinement matched again (``refined``: :attr:`mapping.lidar_slam.SlamConfig.refine_online_nodes`;
none once the graph has settled), the pass's ATE
(the filter's pose, the robot's published pose, from the truth's first pose), the process's
RSS at the pass's end, and how far the SLAM's graph moved the pass's scans after the filter had
mapped them (``moved_after_mapping_m_p90`` / ``_max``, at the end of the run: the map built on
them stays where they were). Per log: ``scans`` (the log's), ``passes``, ``scans_fed``,
``scans_mapped``, ``ms_per_scan_first`` / ``ms_per_scan_last`` (first and last pass, input
stage and filter; "first" is the first pass that mapped a scan, as a short log's first pass may
only have been held for the calibrations; None for a pass that mapped nothing) and
``ms_growth`` (last / first), ``ate_rmse_m`` (every mapped scan),
``ate_rmse_m_first`` / ``ate_rmse_m_last``, ``map_precision_first`` / ``map_precision_last`` (the
best map after the first and the last pass against the log's scan endpoints at the true poses,
within 0.2 m, as ``wiremap bench lidar`` scores it), ``rss_mb_first`` / ``rss_mb_last`` and
``rss_mb_per_1000_scans`` (the least-squares slope of RSS over scans mapped, after the first
pass), ``moved_after_mapping_m_p90_first`` (the first pass's), ``loops``, ``loops_settled``,
``graph_first`` / ``graph_last``, ``revisits``, ``refined``, ``cpu_s``.

Output: a table (a row per log), progress on stderr, ``NAME-pass-K.png`` in ``--out`` (the map
after the first pass that mapped and after the last, over the log's real scan endpoints at the
true poses, with that pass's path where the SLAM's graph has it then), and with ``--json`` one
last line::

    {"logs": {NAME: {...}}, "median": {...}, "passes": N, "settings": {...}}
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import time
from dataclasses import replace
from typing import Any

import numpy as np

from agents.argtypes import non_negative_int, positive_int
from agents.bench.common import Progress, aligned_rows, fmt_cell
from agents.bench.lidar import add_log_arguments, find_logs, log_name, pose_array, settings_for
from agents.errors import UserError

HELP = "a live robot's mapper over a long shift: real logs driven back and forth, time and memory per pass"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_log_arguments(parser, "CARMEN logs (.log or .log.gz) with a truth")
    parser.add_argument("--passes", type=positive_int, default=10, metavar="N",
                        help="times each log is driven, forward then back (default 10)")
    parser.add_argument("--seed", type=non_negative_int, default=1,
                        help="random seed of the filter (default 1)")
    parser.add_argument("--particles", type=positive_int, default=5,
                        help="particles (default 5, as wiremap robot)")
    parser.add_argument("--threshold", type=float, default=0.2, metavar="M",
                        help="merge threshold, metres (default 0.2, as wiremap robot)")
    parser.add_argument("--min-travel", type=float, default=0.5, metavar="M",
                        help="the motion filter's distance (default 0.5, as wiremap robot)")
    parser.add_argument("--min-turn", type=float, default=10.0, metavar="DEG",
                        help="the motion filter's turn (default 10, as wiremap robot)")
    parser.add_argument("--calibration-scans", type=positive_int, default=30, metavar="N",
                        help="scans held for the calibrations (default 30, as wiremap robot)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                        help="override one setting of the lidar-slam-online profile; repeatable")
    parser.add_argument("--jobs", type=positive_int, default=1, metavar="N",
                        help="logs at once, each in its own process (default 1)")
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")
    parser.add_argument("--out", default="out/bench-live", metavar="DIR",
                        help="where the PNGs go: each log's map after its first and its last pass")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def shift(scans: list[Any], passes: int) -> list[tuple[int, Any]]:
    """The log's scans forward, back, forward ... ``passes`` times, as ``(index in the log,
    scan)``; the scans' times made to increase by 0.1 s a scan, and their beams simultaneous
    (``time_increment`` 0: driven backwards, a scan's beams would come in the wrong order for
    the live de-skew; :func:`run_log` de-skews the log once, forwards, before)."""
    order: list[int] = []
    for p in range(passes):
        order += list(range(len(scans))) if p % 2 == 0 else list(range(len(scans) - 1, -1, -1))
    return [(k, replace(scans[k], t=0.1 * i, time_increment=0.0)) for i, k in enumerate(order)]


def _rss_mb() -> float:
    from agents.bench.common import rss_bytes

    got = rss_bytes(os.getpid())
    if got is None:  # no /proc: the peak, which is what the robot must have anyway
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return got / 2**20


def run_log(path: str, *, passes: int, seed: int, particles: int, threshold: float, min_travel: float,
            min_turn_deg: float, settings: dict[str, Any],
            progress: bool = False, out: str | None = None) -> dict[str, Any]:
    """One log's shift (see the module notes); runs in a worker process of its own (``progress``:
    a live line on its stderr)."""
    from agents import mapping_run as mr
    from agents.files.carmen import read_carmen_log, scan_truth
    from agents.fleet.live_lidar import live_filter
    from mapping.lidar_metrics import ate, map_precision, scan_endpoints
    from mapping.se2 import Pose

    log = read_carmen_log(path)
    truth = scan_truth(log)
    if truth is None:
        raise UserError(f"{path}: no truth (NAME.truth.tsv or TRUEPOS lines)")
    scans = list(log.scans)
    if not scans:
        raise UserError(f"{path}: no laser scans in the log")
    filter_overrides, extract, frontend = mr.split_profile(settings)
    scans = mr.deskewed(scans, frontend)  # forwards, once (shift's times are not the log's)
    filt, cap = live_filter(scans[0], particles, threshold, seed, filter_overrides)  # as the robot's
    live = mr.LiveInputs(max_range=cap, extract=extract, frontend=frontend, min_travel=min_travel,
                         min_turn=math.radians(min_turn_deg))
    endpoints = scan_endpoints(pose_array(truth), [s.ranges for s in scans], [s.angles for s in scans],
                               max_range=cap)
    origin = truth[0]
    waiting: list[int] = []  # log indexes of the scans taken whose inputs have not come out yet
    est: list[tuple[int, Pose]] = []
    rows: list[dict[str, Any]] = []
    cpu_in = cpu_filter = 0.0
    mapped_before = loops_before = settled_before = revisits_before = refined_before = 0
    fed = shift(scans, passes)
    per_pass = len(scans)
    cpu0 = time.process_time()
    rss_at: list[tuple[int, float]] = []
    show = Progress(progress, live=True)
    pictures: list[tuple[int, Any, list[tuple[int, Any]], float]] = []  # (pass, map, its poses, precision)
    name = log_name(path)

    def take(inputs: list[Any]) -> None:
        nonlocal cpu_filter
        for inp in inputs:
            j = waiting.pop(0)
            t0 = time.process_time()
            mr.feed(filt, inp)
            cpu_filter += time.process_time() - t0
            est.append((j, origin.compose(filt.pose)))

    for i, (k, ls) in enumerate(fed):
        before = live.skipped
        t0 = time.process_time()
        ready = live.add(ls)
        cpu_in += time.process_time() - t0
        if live.skipped == before:
            waiting.append(k)
        take(ready)
        show.update(f"{name}: pass {i // per_pass + 1}/{passes}, scan {i + 1}/{len(fed)}, {len(est)} mapped")
        if (i + 1) % per_pass == 0 or i + 1 == len(fed):
            if i + 1 == len(fed):
                t0 = time.process_time()
                ready = live.finish()
                cpu_in += time.process_time() - t0
                take(ready)
            slam = live.slam
            mapped = len(est) - mapped_before
            part = est[mapped_before:]
            loops = len(slam.loops) if slam is not None else 0
            settled = slam.settled if slam is not None else 0
            graph = len(slam.poses) if slam is not None else 0
            revisits = slam.skipped if slam is not None else 0
            refined = slam.refined if slam is not None else 0
            rss = _rss_mb()
            rss_at.append((len(est), rss))
            scored = (mapped and not any(r["scans_mapped"] for r in rows)) or len(rows) == passes - 1
            precision = None
            if scored:  # the first pass that mapped and the last (a second on a long log): scored, drawn
                world = filt.best.transformed(origin)
                precision = map_precision(world, endpoints, 0.2)
                if out is not None:
                    drawn = part
                    if slam is not None:  # the pass's scans where the graph has them now, as the map
                        now = slam.scan_poses()[mapped_before:len(est)]
                        drawn = [(j, origin.compose(Pose(*map(float, q))))
                                 for (j, _), q in zip(part, now, strict=True)]
                    pictures.append((len(rows) + 1, world, drawn, precision))
            rows.append({
                "pass": len(rows) + 1,
                "scans_mapped": mapped,
                # None for a pass that mapped nothing (its scans all held for the calibrations)
                "ms_input": 1000.0 * cpu_in / mapped if mapped else None,
                "ms_filter": 1000.0 * cpu_filter / mapped if mapped else None,
                "loops": loops - loops_before,
                "loops_settled": settled - settled_before,
                "graph": graph,
                "revisits": revisits - revisits_before,
                "refined": refined - refined_before,
                "ate_rmse_m": _ate(part, truth, ate),
                "map_precision": precision,
                "rss_mb": rss,
            })
            cpu_in = cpu_filter = 0.0
            mapped_before, loops_before, settled_before, revisits_before, refined_before = (
                len(est), loops, settled, revisits, refined)
    show.clear()
    if out is not None:
        _pictures(out, name, pictures, endpoints, pose_array(truth))
    # How far the SLAM's graph moved each pass's scans after the filter had mapped them at the
    # pose it gave them then (the k-th scan mapped is the SLAM's k-th scan): what the map must
    # follow (frontend.follow_graph) or, where it does not, the walls mapped again beside it.
    slam = live.slam
    if slam is not None:
        moved = np.hypot(*(np.asarray(slam.online)[:, :2] - slam.scan_poses()[:, :2]).T)
        lo = 0
        for r in rows:
            hi = lo + r["scans_mapped"]
            part_moved = moved[lo:hi]
            r["moved_after_mapping_m_p90"] = float(np.percentile(part_moved, 90)) if len(part_moved) else None
            r["moved_after_mapping_m_max"] = float(part_moved.max()) if len(part_moved) else None
            lo = hi
    # The first pass that mapped a scan is the baseline (a short log's first pass may only
    # have been held for the calibrations).
    first = next((r for r in rows if r["scans_mapped"]), rows[0])
    last = rows[-1]
    ms_first = first["ms_input"] + first["ms_filter"] if first["scans_mapped"] else None
    ms_last = last["ms_input"] + last["ms_filter"] if last["scans_mapped"] else None
    slope = _slope(rss_at[1:]) if len(rss_at) >= 3 else None
    return {
        "scans": len(scans), "passes": passes, "scans_fed": len(fed), "scans_mapped": len(est),
        "ms_per_scan_first": ms_first, "ms_per_scan_last": ms_last,
        "ms_growth": ms_last / ms_first if ms_first and ms_last is not None else None,
        "ate_rmse_m": _ate(est, truth, ate), "ate_rmse_m_first": first["ate_rmse_m"],
        "ate_rmse_m_last": last["ate_rmse_m"],
        "map_precision_first": first["map_precision"], "map_precision_last": last["map_precision"],
        "rss_mb_first": first["rss_mb"], "rss_mb_last": last["rss_mb"],
        "rss_mb_per_1000_scans": None if slope is None else 1000.0 * slope,
        "moved_after_mapping_m_p90_first": first.get("moved_after_mapping_m_p90"),
        "loops": sum(r["loops"] for r in rows), "loops_settled": sum(r["loops_settled"] for r in rows),
        "graph_first": first["graph"], "graph_last": last["graph"],
        "revisits": sum(r["revisits"] for r in rows),
        "refined": sum(r["refined"] for r in rows),
        "cpu_s": time.process_time() - cpu0, "by_pass": [_rounded(r) for r in rows],
    }


def _pictures(out: str, name: str, pictures: list[tuple[int, Any, list[tuple[int, Any]], float]],
              endpoints: np.ndarray, truth_xyt: np.ndarray) -> None:
    """``NAME-pass-K.png`` in ``out`` for each scored pass: the map after it over the log's real
    scan endpoints at the true poses, the true path and that pass's estimated path."""
    from pathlib import Path

    from agents.bench.lidar_png import lidar_png
    from agents.files.io import write_atomic

    for k, world, part, precision in pictures:
        est = pose_array([p for _, p in part])[:, :2]
        title = f"{name} after pass {k}: precision {precision:.2f}"
        write_atomic(Path(out) / f"{name}-pass-{k}.png", lidar_png(world, endpoints, truth_xyt[:, :2], est,
                                                                  title=title))


def _ate(part: list[tuple[int, Any]], truth: list[Any], ate: Any) -> float | None:
    if not part:
        return None
    return float(ate(pose_array([p for _, p in part]), pose_array([truth[j] for j, _ in part]))[0])


def _slope(points: list[tuple[int, float]]) -> float | None:
    """Least-squares slope of ``(x, y)`` points, or None when the x do not vary."""
    x = np.array([p[0] for p in points], dtype=np.float64)
    y = np.array([p[1] for p in points], dtype=np.float64)
    if np.ptp(x) == 0:
        return None
    return float(np.polyfit(x, y, 1)[0])


def _rounded(d: dict[str, Any]) -> dict[str, Any]:
    """Floats to 6 decimals, a non-finite one (the precision of a map without walls) None: the
    JSON line stays JSON."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else round(v, 6) if isinstance(v, float)
                else v) for k, v in d.items()}


MEDIAN_KEYS = ("ms_per_scan_first", "ms_per_scan_last", "ms_growth", "ate_rmse_m", "ate_rmse_m_first",
               "ate_rmse_m_last", "map_precision_first", "map_precision_last", "rss_mb_per_1000_scans",
               "moved_after_mapping_m_p90_first")


def run(args: argparse.Namespace) -> int:
    import multiprocessing

    from agents import mapping_run as mr

    if not (math.isfinite(args.threshold) and args.threshold > 0):
        raise UserError(f"--threshold must be a number > 0, got {args.threshold}")
    if not (math.isfinite(args.min_travel) and math.isfinite(args.min_turn)
            and args.min_travel >= 0 and args.min_turn >= 0):
        raise UserError("--min-travel and --min-turn must be numbers >= 0")
    paths = find_logs(list(args.logs), args.data)
    settings = settings_for("lidar-slam-online",
                            [f"frontend.calibration_scans={args.calibration_scans}", *args.sets])
    try:  # what the live stage refuses (a SLAM that is not online, no calibration scans), here
        _, extract, frontend = mr.split_profile(settings)
        mr.LiveInputs(max_range=None, extract=extract, frontend=frontend)
    except ValueError as exc:
        raise UserError(f"--set: {exc}") from None
    job = functools.partial(run_log, passes=args.passes, seed=args.seed, particles=args.particles,
                            threshold=args.threshold, min_travel=args.min_travel, min_turn_deg=args.min_turn,
                            settings=settings, out=str(args.out))
    say = Progress(not args.quiet, live=False)
    results: dict[str, dict[str, Any]] = {}
    t0 = time.perf_counter()

    def done(name: str, r: dict[str, Any]) -> None:
        results[name] = r = _rounded(r)
        ms = f"{fmt_cell(r['ms_per_scan_first'], '{:.1f}')} -> {fmt_cell(r['ms_per_scan_last'], '{:.1f}')}"
        say.line(f"{name}: {r['scans_mapped']} scans mapped in {args.passes} passes, {ms} ms/scan, "
                 f"RSS {r['rss_mb_first']:.0f} -> {r['rss_mb_last']:.0f} MB "
                 f"[{len(results)}/{len(paths)} logs, {time.perf_counter() - t0:.0f} s]")

    if len(paths) == 1:  # here: the RSS is this process's, one log's
        done(log_name(paths[0]), job(str(paths[0]), progress=not args.quiet))
    else:
        # A fresh process per log (maxtasksperchild=1), so that each log's RSS is its own; a
        # log that fails ends the run at once (leaving the block terminates the others).
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(processes=min(args.jobs, len(paths)), maxtasksperchild=1) as pool:
            pending = [(log_name(p), pool.apply_async(job, (str(p),))) for p in paths]
            for name, res in pending:
                done(name, res.get())
    med: dict[str, Any] = {}
    for key in MEDIAN_KEYS:
        vals = [r[key] for r in results.values() if r.get(key) is not None]
        med[key] = round(float(np.median(vals)), 6) if vals else None
    print(format_table(results, med, args.passes))
    print(f"PNGs in {args.out}/")
    if args.json:
        print(json.dumps({"logs": results, "median": med, "passes": args.passes, "settings": settings}))
    return 0


def format_table(logs: dict[str, dict[str, Any]], med: dict[str, Any], passes: int) -> str:
    last = f"pass {passes}"
    head = ["log", "mapped", "graph first", last, "ms/scan first pass", last, "growth", "ATE m first", last,
            "precision first", last, "RSS MB first", last, "MB/1000 scans", "moved m p90 first",
            "loops (settled)"]
    cells = (("ms_per_scan_first", "{:.1f}"), ("ms_per_scan_last", "{:.1f}"), ("ms_growth", "{:.2f}"),
             ("ate_rmse_m_first", "{:.3f}"), ("ate_rmse_m_last", "{:.3f}"), ("map_precision_first", "{:.3f}"),
             ("map_precision_last", "{:.3f}"), ("rss_mb_first", "{:.0f}"), ("rss_mb_last", "{:.0f}"),
             ("rss_mb_per_1000_scans", "{:.1f}"), ("moved_after_mapping_m_p90_first", "{:.3f}"))
    rows = [[n, str(r["scans_mapped"]), str(r["graph_first"]), str(r["graph_last"]),
             *(fmt_cell(r[k], f) for k, f in cells), f"{r['loops']} ({r['loops_settled']})"]
            for n, r in logs.items()]
    rows.append(["median", "", "", "", *(fmt_cell(med.get(k), f) for k, f in cells), ""])
    return aligned_rows([head, *rows])
