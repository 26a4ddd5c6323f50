"""``wiremap bench accuracy``: map quality over seeds, the filter against a single-hypothesis baseline.

For each seed a robot drives its coverage route through the world; the scans are simulated once
and fed to the particle filter (and, with ``--baseline``, to a single-hypothesis mapper: one
particle, no mutation, on the identical scans). The best particle's map is scored against the
truth (:func:`mapping.metrics.evaluate` at the merge threshold as resolution, as the paper
does). Prints an aligned table and, with ``--json``, one JSON object on the last line with the
medians over seeds::

    {"world", "sensor", "seeds", "particles", "cell_error", "wall_precision", "wall_recall",
     "mean_dist_m", "p95_dist_m", "mean_dist_aligned_m", "particle_bytes", "steps", "updates_per_s"
     [, "baseline": {...}] [, "realistic": {"sensor": "lidar-real", ...same medians...,
     ["baseline": {...}]}]}

``mean_dist_aligned_m`` (added) is the mean distance after the rigid motion that lays the map
best onto the truth (:func:`mapping.metrics.align_to_truth`): how much of ``mean_dist_m`` is the
map being turned or shifted as a whole. ``mean_dist_m`` stays the measure (the start pose is
known, so the map's frame is the truth's). Each seed's map is written as a PNG (map over truth) to ``--out``.

``--wall-tol M`` scores wall precision and recall at ``M`` metres instead of twice the merge
threshold (the paper's cell metric, the default); the JSON then also has ``"wall_tol_m"``.
The issue's target for world files (95 % at 0.2 m) is ``--wall-tol 0.2``.

Sensors (``--sensor``): ``corners`` (the corner sensor, the default), ``lidar`` and
``lidar-real`` (:data:`agents.mapping_run.SENSORS`). ``--sensor lidar`` runs every seed twice,
with the clean lidar and with the realistic one (:mod:`agents.sim.real_lidar`: range noise
growing with range, dropouts, max-range bursts, glass, clutter, people; the seed is also the
scene's), and reports both: the table gains a ``sensor`` column with a row per sensor, the JSON's
top-level figures stay the clean lidar's, and ``"realistic": {...}`` holds the same medians
for the realistic one (with ``"baseline"`` inside it under ``--baseline``). ``--sensor
lidar-real`` runs the realistic lidar alone (its figures at the top level).

``--lidar-set GROUP.KEY=VALUE`` (repeatable) changes the realistic lidar
(:class:`agents.sim.real_lidar.RealLidarConfig`: ``noise.*`` for :class:`~agents.sim.real_lidar.RangeNoise`,
``scene.*`` for :class:`~agents.sim.real_lidar.SceneConfig`), e.g. ``--lidar-set
scene.glass_share=0`` for a building without glass; the JSON's ``"realistic"`` then has
``"lidar_settings"``.

``--profile lidar`` applies the real-lidar profile (:func:`agents.mapping_run.lidar_profile`:
its filter settings under ``--params`` and ``--set``, its ``extract.*`` settings to the
simulated lidars' split-and-merge); the JSON then has ``"profile": "lidar"``. ``--set
extract.KEY=VALUE`` sets one split-and-merge setting (:class:`mapping.extract.ExtractConfig`) of the
simulated lidars, on top of the profile's; the JSON then has ``"extract_overrides"``.

``--params FILE`` and ``--set group.key=value`` change the filter's settings
(:mod:`agents.params`; ``--particles`` and ``--merge-threshold`` are shorthands for ``--set
particles=`` and ``--set merge_threshold=``, and the merge threshold in effect is also the metric
resolution). The baseline runs the same configuration, then forced to one particle and no
mutation. The JSON then also has ``"config_overrides"``: the settings from ``--params`` and
``--set`` as applied (``{dotted key: value}``; pass each as ``--set`` to run it again).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.argtypes import positive_int
from agents.bench.common import aligned_rows, fmt_cell
from agents.errors import UserError
from agents.params import ConfigArgs, add_config_arguments, resolve

if TYPE_CHECKING:
    from mapping.filter import FilterConfig

HELP = "map quality over seeds, filter vs single-hypothesis baseline"

METRICS = ("cell_error", "wall_precision", "wall_recall", "mean_dist_m", "p95_dist_m")
KEYS = (*METRICS, "mean_dist_aligned_m", "particle_bytes", "steps", "updates_per_s")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", required=True, metavar="NAME|FILE", help="built-in world or world file")
    parser.add_argument("--seeds", type=int, default=3, metavar="K", help="number of seeds (default 3)")
    parser.add_argument("--first-seed", type=int, default=0, metavar="S", help="seeds S..S+K-1 (default 0)")
    parser.add_argument("--sensor", choices=("corners", "lidar", "lidar-real"), default="corners",
                        help="corner sensor (default), lidar (reports the clean and the realistic "
                             "lidar) or lidar-real (the realistic lidar alone)")
    parser.add_argument("--lidar-set", action="append", default=[], metavar="GROUP.KEY=VALUE",
                        dest="lidar_sets",
                        help="one setting of the realistic lidar, e.g. scene.glass_share=0 or "
                             "noise.p_dropout=0.01 (repeatable)")
    parser.add_argument("--profile", choices=("none", "lidar"), default="none",
                        help="lidar: the real-lidar profile (filter settings and split-and-merge) "
                             "on top of the defaults (default none)")
    parser.add_argument("--particles", type=int, default=None,
                        help="particles (default 10; 6 for worlds over 100 m, as the paper)")
    parser.add_argument("--merge-threshold", type=float, default=None, metavar="M",
                        help="merge threshold and metric resolution (default 0.2, 0.4 for worlds over 100 m)")
    parser.add_argument("--steps", type=positive_int, default=None, metavar="N",
                        help="stop each run after N scans")
    parser.add_argument("--wall-tol", type=float, default=None, metavar="M",
                        help="wall precision/recall tolerance, metres (default twice the merge threshold)")
    parser.add_argument("--baseline", action="store_true", help="also run the single-hypothesis baseline")
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")
    parser.add_argument("--out", default="out/bench-accuracy", metavar="DIR", help="where the PNGs go")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")
    parser.add_argument("--jobs", type=int, default=1, metavar="N",
                        help="run N seeds at once in separate processes (default 1; the runs then "
                             "share the cores, so updates_per_s is lower than alone)")
    add_config_arguments(parser, "--particles, --merge-threshold")


def run_one(
    world: Any, inputs: list[Any], cfg: FilterConfig, seed: int, tol: float | None = None,
) -> tuple[dict[str, Any], Any, list[tuple[float, float]]]:
    """Run one filter of configuration ``cfg`` over ``inputs``; returns (result row, best map,
    trajectory xy). The map is scored at ``cfg.merge_threshold`` as resolution, walls at ``tol``
    metres (default twice that, :func:`mapping.metrics.evaluate`)."""
    from agents.mapping_run import run_filter, seeds_for
    from mapping.filter import WireframeFilter
    from mapping.metrics import align_to_truth, distance_to_truth, evaluate

    thr = cfg.merge_threshold
    filt = WireframeFilter(cfg, seeds_for(seed)["filter"], initial_pose=inputs[0].true_pose)
    busy = 0.0
    traj: list[tuple[float, float]] = []
    for st in run_filter(inputs, filt):
        busy += st.step_s
        traj.append((st.pose.x, st.pose.y))
    best = filt.best
    metrics = evaluate(world.truth, best, thr, tol) if best.n_edges else dict.fromkeys(METRICS, math.nan)
    aligned = math.nan
    if best.n_edges:
        aligned = distance_to_truth(world.truth,
                                    best.transformed(align_to_truth(world.truth, best, thr)), thr)[0]
    row = {
        **{k: float(v) for k, v in metrics.items()},
        "mean_dist_aligned_m": aligned,
        "particle_bytes": filt.memory_bytes(),
        "steps": len(inputs),
        "updates_per_s": len(inputs) / busy if busy > 0 else math.nan,
    }
    return row, best, traj


def _median(rows: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k in KEYS:
        vals = np.array([r[k] for r in rows], dtype=np.float64)
        vals = vals[np.isfinite(vals)]
        m = float(np.median(vals)) if len(vals) else math.nan
        out[k] = round(m) if k in ("particle_bytes", "steps") and math.isfinite(m) else _round(m)
    return out


def _round(v: float) -> float | None:
    return None if not math.isfinite(v) else round(v, 6)


def format_table(rows: list[tuple[str, str, dict[str, Any]]], sensors: list[str] | None = None) -> str:
    """An aligned text table: one line per (seed, method) row; with ``sensors`` (one per row) a
    ``sensor`` column after the seed."""
    head = ["seed", "method", "cell_err", "precision", "recall", "mean_d_m", "p95_d_m", "aligned_m", "bytes",
            "steps", "ups"]
    if sensors is not None:
        head.insert(1, "sensor")
    lines = [head]
    for k, (seed, method, r) in enumerate(rows):
        line = [
            seed,
            method,
            fmt_cell(r["cell_error"], "{:.2%}"),
            fmt_cell(r["wall_precision"], "{:.3f}"),
            fmt_cell(r["wall_recall"], "{:.3f}"),
            fmt_cell(r["mean_dist_m"], "{:.3f}"),
            fmt_cell(r["p95_dist_m"], "{:.3f}"),
            fmt_cell(r.get("mean_dist_aligned_m"), "{:.3f}"),
            str(r["particle_bytes"]),
            str(r["steps"]),
            fmt_cell(r["updates_per_s"], "{:.1f}"),
        ]
        if sensors is not None:
            line.insert(1, sensors[k])
        lines.append(line)
    return aligned_rows(lines, left=3 if sensors is not None else 2)


def sensors_for(sensor: str) -> list[str]:
    """The simulated sensors a ``--sensor`` choice runs: ``lidar`` runs the clean and the
    realistic lidar."""
    return ["lidar", "lidar-real"] if sensor == "lidar" else [sensor]


def run_seed(
    world_arg: str, sensor: str, steps: int | None, seed: int, cfg: FilterConfig,
    baseline: bool, out: str, tol: float | None = None, extract: Any = None, real: Any = None,
) -> list[tuple[str, str, dict[str, Any], float]]:
    """One seed: for each sensor of :func:`sensors_for`, simulate the scans once (the sensor's
    range is ``cfg.max_range``; ``extract``: the lidars' split-and-merge settings; ``real``: the
    realistic lidar's :class:`~agents.sim.real_lidar.RealLidarConfig`), run the
    filter of configuration ``cfg`` (and the baseline, the same with one particle and no
    mutation, on the same scans), write each map's PNG to ``out``. Returns ``(sensor, method,
    row, seconds since start)`` per run.
    Loads the world itself, so that it can run in a worker process (``--jobs``)."""
    from agents import mapping_run as mr
    from agents.files.io import write_atomic
    from agents.files.render import map_png
    from agents.sim.world import load_world

    t0 = time.perf_counter()
    world = load_world(world_arg)
    done = []
    for name in sensors_for(sensor):
        options = mr.SimOptions(sensor=name, steps=steps, max_range=cfg.max_range, extract=extract,
                                real=real if name == "lidar-real" else None)
        try:
            inputs = list(mr.simulate(world, options, seed))
        except ValueError as exc:
            raise UserError(f"{world_arg}: {exc}") from None
        configs = [("filter", cfg)] + (
            [("baseline", replace(cfg, particles=1, mutate=False))] if baseline else []
        )
        for method, c in configs:
            row, best, traj = run_one(world, inputs, c, seed, tol)
            png = Path(out) / f"{world.name}-{name}-seed{seed}-{method}.png"
            write_atomic(png, map_png(best, truth=world.truth, trajectory=np.asarray(traj)))
            done.append((name, method, row, time.perf_counter() - t0))
    return done


def _lidar_settings(items: list[str]) -> tuple[dict[str, str], Any]:
    """``({key: value}, RealLidarConfig)`` from ``--lidar-set`` items (None without any).

    Raises
    ------
    UserError
        An item without ``=``, an unknown key or a bad value.
    """
    from agents.sim.real_lidar import RealLidarConfig
    from mapping.config import ConfigError, with_overrides

    settings: dict[str, str] = {}
    for item in items:
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise UserError(f"--lidar-set {item!r}: expected GROUP.KEY=VALUE")
        settings[key.strip()] = value.strip()
    if not settings:
        return settings, None
    try:
        return settings, with_overrides(RealLidarConfig(), settings)
    except (ConfigError, ValueError) as exc:
        raise UserError(f"--lidar-set: {exc}") from None


def run(args: argparse.Namespace) -> int:
    from concurrent.futures import ProcessPoolExecutor

    from agents import mapping_run as mr
    from agents.sim.world import load_world

    if args.seeds < 1:
        raise UserError(f"--seeds must be >= 1, got {args.seeds}")
    if args.jobs < 1:
        raise UserError(f"--jobs must be >= 1, got {args.jobs}")
    if args.wall_tol is not None and not (math.isfinite(args.wall_tol) and args.wall_tol > 0):
        raise UserError(f"--wall-tol must be a positive number of metres, got {args.wall_tol}")
    if args.particles is not None and args.particles < 1:
        raise UserError(f"--particles must be >= 1, got {args.particles}")
    cargs = ConfigArgs.from_args(args)
    # --set extract.KEY=VALUE is split-and-merge's (the simulated lidars'), not the filter's
    extract_sets = {k: v for k, v in cargs.set_values.items() if k.startswith("extract.")}
    if extract_sets:
        cargs = dataclasses.replace(
            cargs, set_values={k: v for k, v in cargs.set_values.items() if k not in extract_sets})
    world = load_world(args.world)
    particles, thr = mr.world_defaults(world)
    flags = {"particles": ("--particles", args.particles),
             "merge_threshold": ("--merge-threshold", args.merge_threshold)}
    profile_filter: dict[str, Any] = {}
    extract = None
    if args.profile == "lidar":
        profile_filter, extract, _ = mr.split_profile(mr.lidar_profile())
    if extract_sets:
        from mapping.config import ConfigError, with_overrides
        from mapping.extract import ExtractConfig

        try:
            extract = with_overrides(extract if extract is not None else ExtractConfig(),
                                     {k.partition(".")[2]: v for k, v in extract_sets.items()})
        except (ConfigError, ValueError) as exc:
            raise UserError(f"--set extract.*: {exc}") from None
    resolved = resolve(
        cargs,
        lambda ov: mr.filter_config_for(particles, thr, mr.SimOptions().max_range,
                                        overrides={**profile_filter, **ov}),
        {k: v for k, v in flags.items() if v[1] is not None},
    )
    cfg = resolved.config
    lidar_settings, real = _lidar_settings(list(args.lidar_sets))
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    job = functools.partial(
        run_seed, str(args.world), args.sensor, args.steps,
        cfg=cfg, baseline=bool(args.baseline), out=str(args.out), tol=args.wall_tol, extract=extract,
        real=real,
    )
    results: dict[int, list[tuple[str, str, dict[str, Any], float]]] = {}

    def report(seed: int, done: list[tuple[str, str, dict[str, Any], float]]) -> None:
        results[seed] = done
        if args.quiet:
            return
        for name, method, row, secs in done:
            what = method if len(sensors_for(args.sensor)) == 1 else f"{name} {method}"
            sys.stderr.write(
                f"seed {seed} {what}: cell error {row['cell_error']:.2%}, "
                f"precision {row['wall_precision']:.3f}, recall {row['wall_recall']:.3f}, "
                f"{row['particle_bytes']} B, {row['updates_per_s']:.1f} ups "
                f"({secs:.0f} s) [{len(results)}/{len(seeds)} seeds]\n"
            )

    if args.jobs == 1 or len(seeds) == 1:
        for seed in seeds:
            report(seed, job(seed))
    else:
        with ProcessPoolExecutor(max_workers=min(args.jobs, len(seeds))) as pool:
            futures = {seed: pool.submit(job, seed) for seed in seeds}
            for seed, fut in futures.items():  # in seed order; later seeds may be done already
                report(seed, fut.result())
    names = sensors_for(args.sensor)
    table: list[tuple[str, str, dict[str, Any]]] = []
    table_sensors: list[str] = []
    rows: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for seed in seeds:
        for name, method, row, _ in results[seed]:
            table.append((str(seed), method, row))
            table_sensors.append(name)
            rows.setdefault((name, method), []).append(row)
    meds = {key: _median(r) for key, r in rows.items()}
    for name in names:
        for method in ("filter", "baseline"):
            if (name, method) in meds:
                table.append(("median", method, meds[(name, method)]))
                table_sensors.append(name)
    out = Path(args.out)
    print(format_table(table, table_sensors if len(names) > 1 else None))
    print(f"PNGs in {out}/")
    first = names[0]
    summary: dict[str, Any] = {
        "world": world.name,
        "sensor": args.sensor,
        "seeds": args.seeds,
        "particles": cfg.particles,
        **meds[(first, "filter")],
    }
    if args.wall_tol is not None:
        summary["wall_tol_m"] = args.wall_tol
    if (first, "baseline") in meds:
        summary["baseline"] = {"particles": 1, **meds[(first, "baseline")]}
    if "lidar-real" in names[1:]:
        realistic: dict[str, Any] = {"sensor": "lidar-real", **meds[("lidar-real", "filter")]}
        if ("lidar-real", "baseline") in meds:
            realistic["baseline"] = {"particles": 1, **meds[("lidar-real", "baseline")]}
        if lidar_settings:
            realistic["lidar_settings"] = lidar_settings
        summary["realistic"] = realistic
    elif lidar_settings and "lidar-real" in names:
        summary["lidar_settings"] = lidar_settings
    if args.profile != "none":
        summary["profile"] = args.profile
    if resolved.recorded:
        summary["config_overrides"] = resolved.recorded
    if extract_sets:
        summary["extract_overrides"] = extract_sets
    if args.json:
        print(json.dumps(summary))
    return 0
