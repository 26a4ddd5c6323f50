"""``wiremap bench scanners``: the real-lidar path on the scanners robots carry, in simulated worlds.

The shared real logs all come from one scanner (a SICK LMS, 180 degrees, a scan every 0.5-1 m).
For each world (``--worlds``), scanner (``--scanners``, :data:`agents.sim.scanner_logs.SCANNERS`)
and seed (``--seeds``), this writes the log that scanner would record driving the world's
coverage route for ``--duration`` seconds (:func:`agents.sim.scanner_logs.write_scanner_log`:
every scan at the scanner's rate, the realistic lidar's noise, drifting wheels) into
``--out/logs/`` and maps it exactly as ``wiremap bench lidar`` maps a real log
(:func:`agents.bench.lidar.run_log`: the same profile, scores and picture; a dense log thinned
by the motion filter first). The logs stay, so ``wiremap map --carmen`` can map them again.

Output: a table of each run and of each scanner's medians over worlds and seeds, a PNG per run
in ``--out``, and with ``--json`` one last line::

    {"runs": {"office/lds-01/s1": {"world", "scanner", "seed", "scans_in_log", "scans", "ate_rmse_m",
              ..., "odometry_ate_rmse_m"}},
     "scanners": {NAME: {median of each number over its runs}}, "median": {...},
     "worlds": [...], "seeds": [...], "duration_s": S, "reversed_sweep": false, "profile": "lidar-slam",
     "settings": {...}}
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

from agents.argtypes import positive_int
from agents.bench.common import Progress, aligned_rows, fmt_cell
from agents.errors import UserError
from agents.mapping_run import LIDAR_PROFILES

HELP = "the real-lidar path on common scanners (SICK, Hokuyo, RPLIDAR, LDS-01) in simulated worlds"

DEFAULT_WORLDS = "office,paper-small"
DEFAULT_SEEDS = "1,2,3"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from agents.sim.scanner_logs import SCANNERS

    parser.add_argument("--scanners", default=",".join(SCANNERS), metavar="A,B",
                        help=f"scanner models (default all: {', '.join(SCANNERS)})")
    parser.add_argument("--worlds", default=DEFAULT_WORLDS, metavar="A,B",
                        help=f"built-in worlds or world files (default {DEFAULT_WORLDS})")
    parser.add_argument("--seeds", default=DEFAULT_SEEDS, metavar="S,T",
                        help=f"seeds of the route, the scene, the wheels and the filter (default "
                             f"{DEFAULT_SEEDS})")
    parser.add_argument("--duration", type=float, default=150.0, metavar="S",
                        help="seconds of driving at 0.5 m/s per log (default 150)")
    parser.add_argument("--reversed-sweep", action="store_true",
                        help="the scanners sweep their beams last bearing first while the logs say first "
                        "bearing first (the TurtleBot3 LDS-01 driver's default order)")
    parser.add_argument("--profile", choices=tuple(LIDAR_PROFILES), default="lidar-slam",
                        help="real-lidar settings, as wiremap bench lidar (default lidar-slam)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                        help="override one setting (dotted key); repeatable")
    parser.add_argument("--jobs", type=positive_int, default=1, metavar="N",
                        help="runs at once in separate processes (default 1)")
    parser.add_argument("--out", default="out/bench-scanners", metavar="DIR",
                        help="where the logs (logs/) and the PNGs go")
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def _names(text: str, flag: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise UserError(f"{flag}: give at least one name")
    if len(set(names)) != len(names):
        raise UserError(f"{flag}: a name given twice")
    return names


def _check(args: argparse.Namespace) -> tuple[list[str], list[str], list[int]]:
    from agents.sim.scanner_logs import SCANNERS
    from agents.sim.world import load_world

    scanners = _names(args.scanners, "--scanners")
    unknown = [s for s in scanners if s not in SCANNERS]
    if unknown:
        raise UserError(f"--scanners: no scanner {unknown[0]!r} (there are {', '.join(SCANNERS)})")
    worlds = _names(args.worlds, "--worlds")
    for w in worlds:
        try:
            load_world(w)
        except (ValueError, OSError) as exc:
            raise UserError(f"--worlds {w}: {exc}") from None
    try:
        seeds = [int(s) for s in _names(args.seeds, "--seeds")]
    except ValueError:
        raise UserError(f"--seeds must be whole numbers, got {args.seeds!r}") from None
    if any(s < 0 for s in seeds):
        raise UserError("--seeds must be >= 0")
    if not (math.isfinite(args.duration) and args.duration > 0):
        raise UserError(f"--duration must be a positive number of seconds, got {args.duration}")
    return scanners, worlds, seeds


def run_one(world: str, scanner: str, seed: int, *, duration: float, out: str,
            settings: dict[str, Any], reversed_sweep: bool = False) -> dict[str, Any]:
    """Write one world's log for one scanner and seed, then map and score it as
    ``wiremap bench lidar`` does. Runs in a worker process too."""
    from agents.bench.lidar import run_log
    from agents.sim.scanner_logs import SCANNERS, log_name, write_scanner_log

    model = SCANNERS[scanner]
    path = Path(out) / "logs" / f"{log_name(world, model, seed)}.log.gz"
    path.parent.mkdir(parents=True, exist_ok=True)
    n = write_scanner_log(world, model, seed, path, duration=duration, reversed_sweep=reversed_sweep)
    row = run_log(str(path), seed=seed, particles=10, steps=None, max_range=20.0, thr=0.2, baseline=False,
                  out=out, settings=settings)
    return {"world": world, "scanner": scanner, "seed": seed, "scans_in_log": n, **row}


def medians(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The median of each number over ``rows`` (:func:`agents.bench.lidar.median`), names left out."""
    from agents.bench.lidar import median

    numbers = [{k: v for k, v in r.items() if k not in ("world", "scanner")} for r in rows]
    return median(numbers)


def format_table(runs: dict[str, dict[str, Any]], by_scanner: dict[str, dict[str, Any]]) -> str:
    head = ["run", "scans", "mapped", "ate_m", "ate_max_m", "rpe_1m_m", "precision", "coverage",
            "aligned", "odom_ate_m", "ms/scan"]
    lines = [head]

    def add(name: str, r: dict[str, Any]) -> None:
        lines.append([
            name, fmt_cell(r.get("scans_in_log"), "{}"), fmt_cell(r.get("scans"), "{}"),
            fmt_cell(r.get("ate_rmse_m"), "{:.3f}"), fmt_cell(r.get("ate_max_m"), "{:.3f}"),
            fmt_cell(r.get("rpe_1m_m"), "{:.3f}"), fmt_cell(r.get("map_precision"), "{:.3f}"),
            fmt_cell(r.get("map_coverage"), "{:.3f}"), fmt_cell(r.get("map_precision_aligned"), "{:.3f}"),
            fmt_cell(r.get("odometry_ate_rmse_m"), "{:.2f}"), fmt_cell(r.get("ms_per_scan"), "{:.0f}"),
        ])

    for name, r in runs.items():
        add(name, r)
    for name, r in by_scanner.items():
        add(f"median {name}", r)
    return aligned_rows(lines, left=1)


def run(args: argparse.Namespace) -> int:
    import functools
    from concurrent.futures import ProcessPoolExecutor

    from agents.bench.lidar import settings_for

    scanners, worlds, seeds = _check(args)
    settings = settings_for(args.profile, list(args.sets))
    job = functools.partial(run_one, duration=float(args.duration), out=str(args.out), settings=settings,
                            reversed_sweep=bool(args.reversed_sweep))
    todo = [(w, s, seed) for s in scanners for w in worlds for seed in seeds]
    say = Progress(not args.quiet, live=False)
    t0 = time.perf_counter()
    runs: dict[str, dict[str, Any]] = {}

    def done(key: tuple[str, str, int], r: dict[str, Any]) -> None:
        name = f"{key[0]}/{key[1]}/s{key[2]}"
        runs[name] = r
        say.line(f"{name}: ATE {r['ate_rmse_m']:.3f} m, precision {r['map_precision']:.3f}, "
                 f"{r['scans']} of {r['scans_in_log']} scans mapped [{len(runs)}/{len(todo)}, "
                 f"{time.perf_counter() - t0:.0f} s]")

    if args.jobs == 1:
        for key in todo:
            done(key, job(*key))
    else:
        with ProcessPoolExecutor(max_workers=min(args.jobs, len(todo))) as pool:
            futures = {key: pool.submit(job, *key) for key in todo}
            for key, fut in futures.items():
                done(key, fut.result())
    by_scanner = {s: medians([r for r in runs.values() if r["scanner"] == s]) for s in scanners}
    print(format_table(runs, by_scanner))
    print(f"logs in {args.out}/logs/, PNGs in {args.out}/")
    if args.json:
        print(json.dumps({"runs": runs, "scanners": by_scanner, "median": medians(list(runs.values())),
                          "worlds": worlds, "seeds": seeds, "duration_s": float(args.duration),
                          "reversed_sweep": bool(args.reversed_sweep),
                          "profile": args.profile, "settings": settings}))
    return 0
