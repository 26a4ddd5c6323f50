"""``wiremap bench speed``: scan updates per second, time per step and peak memory.

Runs the particle filter (10 particles by default) on ``paper-small`` and on ``museum``, each in
its own child process pinned to one core (``os.sched_setaffinity``) with single-threaded BLAS,
so that peak RSS is per world and the rate is a one-core rate. The scans are simulated before
the clock starts; only :meth:`mapping.filter.WireframeFilter.step` is timed.

What is timed: on ``paper-small`` its whole coverage route (``--steps``, 400 by default, more
than the route has); on ``museum`` a *representative* stretch, the ``--steps`` scans after a
warm-up of ``--museum-warmup`` scans (default 2000: steps 2000-2399, when the map already
holds a few hundred walls and the robot has left the first corridor), because the first few
hundred scans of a large world run on a small map and would flatter the ratio. Prints a table
and, with ``--json``, one JSON object on the last line::

    {"paper_small": {"updates_per_s", "step_ms_p50", "step_ms_p95", "peak_rss_mb"},
     "museum": {...}, "museum_to_small_step_ratio"}

``museum_to_small_step_ratio`` is museum's median step time over paper-small's: the time per
step should not grow with the size of the map.

With ``--seeds K`` each world runs K seeds (``--seed`` .. ``--seed`` + K - 1, one child process
each, one after another) and every figure is the median over them (the ratio is that of the
two medians; ``"seeds": K`` is added to the JSON). The time per step follows how many distinct
particles a run keeps in the timed stretch, which differs from seed to seed (museum
``step_ms_p50`` 5.4-9.0 ms over seeds 0-2 on one machine), so one seed is a noisy figure.

With ``--pieces`` it also times, in this process, the pieces around the filter whose speed
the tests used to assert (a test asserts what a piece does; how fast it does it is a figure
here), and adds them to the JSON as ``"pieces"`` (the best of a few repeats of each)::

    {"raycast_ms": ..., "extract_ms": ..., "evaluate_museum_ms": ..., "render_museum_ms": ...,
     "codec_reject_claim_us": ..., "plan_route_s": {"<world>": ..., ...}}

* ``raycast_ms``: one 361-beam lidar scan (:func:`agents.sim.lidar.raycast`) among 100 random
  walls (about 1 ms on an idle core);
* ``extract_ms``: split-and-merge corners (:func:`mapping.extract.extract_corners`) of one
  ray-cast paper-small scan at 1 cm range noise (about 1 ms);
* ``evaluate_museum_ms``: :func:`mapping.metrics.evaluate` of the museum's walls moved by
  0.15 m noise against its truth (about 0.2 s);
* ``render_museum_ms``: the museum as a 1000-pixel PNG (:func:`agents.files.render.map_png`);
* ``codec_reject_claim_us``: rejecting a map body that claims a million vertices in 100
  bytes (:class:`wire_codec.LimitError`, before anything is allocated);
* ``plan_route_s``: planning the coverage route of each built-in world (a few seconds on an
  idle machine for the largest).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from typing import Any

import numpy as np

from agents.argtypes import non_negative_int
from agents.errors import UserError

HELP = "scan updates per second, step time, peak RSS"

WORLDS = (("paper_small", "paper-small"), ("museum", "museum"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--particles", type=int, default=10, help="particles (default 10)")
    parser.add_argument("--steps", type=int, default=400, metavar="N",
                        help="timed scans per world (default 400)")
    parser.add_argument("--warmup", type=int, default=0, metavar="W",
                        help="paper-small: scans run before the timed ones (default 0)")
    parser.add_argument("--museum-warmup", type=int, default=2000, metavar="W",
                        help="museum: scans run before the timed ones, to grow the map first (default 2000)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="first seed (default 0)")
    parser.add_argument("--seeds", type=int, default=1, metavar="K",
                        help="seeds per world; figures are medians over them (default 1)")
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")
    parser.add_argument("--pieces", action="store_true",
                        help="also time ray casting, corner extraction, metrics, rendering, the codec's "
                             "rejection of a huge claim and route planning (\"pieces\" in the JSON)")
    parser.add_argument("--child", metavar="WORLD", help=argparse.SUPPRESS)


def measure(world_spec: str, particles: int, steps: int, warmup: int, seed: int) -> dict[str, Any]:
    """Time the filter on one world in this process."""
    from agents import mapping_run as mr
    from agents.sim.world import load_world
    from mapping.filter import WireframeFilter

    world = load_world(world_spec)
    thr = mr.default_merge_threshold(world)
    options = mr.SimOptions(steps=steps + warmup)
    inputs = list(mr.simulate(world, options, seed))
    cfg = mr.filter_config_for(particles, thr, options.max_range)
    filt = WireframeFilter(cfg, mr.seeds_for(seed)["filter"], initial_pose=inputs[0].true_pose)
    times = []
    cpu0 = 0.0
    for k, inp in enumerate(inputs):
        if k == warmup:
            cpu0 = time.process_time()
        t0 = time.perf_counter()
        filt.step(inp.odometry, inp.scan)
        if k >= warmup:
            times.append(time.perf_counter() - t0)
    cpu = time.process_time() - cpu0
    t = np.asarray(times)
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "updates_per_s": round(len(t) / float(t.sum()), 2),
        "step_ms_p50": round(float(np.median(t)) * 1e3, 3),
        "step_ms_p95": round(float(np.percentile(t, 95)) * 1e3, 3),
        "peak_rss_mb": round(rss_kb / 1024.0, 1),
        "cpu_updates_per_s": round(len(t) / cpu, 2) if cpu > 0 else None,
        "steps": len(t),
        "first": min(warmup, len(inputs)),
        "map_vertices": filt.best.n_vertices,
        "particle_bytes": filt.memory_bytes(),
    }


def _best_s(fn: Any, repeat: int, number: int = 1) -> float:
    """The best over ``repeat`` runs of the mean wall time of ``number`` calls of ``fn``, in seconds."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def pieces() -> dict[str, Any]:
    """Time the pieces around the filter in this process (module docstring, ``--pieces``)."""
    import wire_codec
    from agents import mapping_run as mr
    from agents.files.render import map_png
    from agents.sim.lidar import LidarConfig, raycast
    from agents.sim.route import plan_route
    from agents.sim.world import builtin_names, load_world
    from mapping.extract import extract_corners
    from mapping.metrics import evaluate
    from mapping.se2 import Pose
    from wire_codec.bits import BitWriter
    from wire_codec.body import decode_body
    from wire_codec.errors import DEFAULT_LIMITS

    out: dict[str, Any] = {}
    rng = np.random.default_rng(0)
    a = rng.uniform(-5, 5, (100, 2))
    walls = np.stack([a, a + rng.uniform(-1, 1, (100, 2))], axis=1)
    lidar = LidarConfig()
    out["raycast_ms"] = round(
        _best_s(lambda: raycast(walls, Pose(0.1, 0.2, 0.3), lidar, rng), 5, 10) * 1e3, 3
    )

    small = load_world("paper-small")
    noisy = LidarConfig(sigma=0.01)
    poses = [inp.true_pose for inp in mr.simulate(small, mr.SimOptions(steps=20), 0)
             if inp.true_pose is not None]
    ranges = [raycast(small.truth.segments(), p, noisy, rng) for p in poses]
    angles = noisy.angles()

    def extract_all() -> None:
        for r in ranges:
            extract_corners(r, angles, noisy.max_range)

    out["extract_ms"] = round(_best_s(extract_all, 3) / len(ranges) * 1e3, 3)

    museum = load_world("museum")
    moved = museum.truth.replace(points=museum.truth.points
                                 + rng.normal(0.0, 0.15, museum.truth.points.shape))
    out["evaluate_museum_ms"] = round(_best_s(lambda: evaluate(museum.truth, moved, 0.4), 3) * 1e3, 1)
    out["render_museum_ms"] = round(
        _best_s(lambda: map_png(museum.truth, truth=museum.truth, max_px=1000), 3) * 1e3, 1
    )

    w = BitWriter()
    w.eg(10**6)
    claim = w.to_bytes() + bytes(100)

    def reject() -> None:
        try:
            decode_body(claim, 200, None, DEFAULT_LIMITS)
        except wire_codec.LimitError:
            return
        raise AssertionError("a million-vertex claim in 100 bytes was not rejected")

    out["codec_reject_claim_us"] = round(_best_s(reject, 5, 100) * 1e6, 1)
    routes: dict[str, float] = {}
    for name in builtin_names():
        world = load_world(name)
        t0 = time.perf_counter()
        plan_route(world, np.random.default_rng(7))
        routes[name] = round(time.perf_counter() - t0, 2)
    out["plan_route_s"] = routes
    return out


def _child(args: argparse.Namespace) -> int:
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    except (AttributeError, OSError):
        pass
    print(json.dumps(measure(args.child, args.particles, args.steps, args.warmup, args.seed)))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.child:
        return _child(args)
    if args.particles < 1 or args.steps < 1 or args.warmup < 0:
        raise UserError("--particles and --steps must be >= 1 and --warmup >= 0")
    if args.seeds < 1:
        raise UserError(f"--seeds must be >= 1, got {args.seeds}")
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env[var] = "1"
    if args.museum_warmup < 0:
        raise UserError("--museum-warmup must be >= 0")
    seeds = range(args.seed, args.seed + args.seeds)
    runs: dict[str, list[dict[str, Any]]] = {key: [] for key, _ in WORLDS}
    for key, spec in WORLDS:
        warmup = args.museum_warmup if key == "museum" else args.warmup
        for seed in seeds:
            cmd = [sys.executable, "-m", "agents", "bench", "speed", "--child", spec, "--particles",
                   str(args.particles), "--steps", str(args.steps), "--warmup", str(warmup),
                   "--seed", str(seed)]
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
            if proc.returncode != 0:
                raise UserError(f"speed run on {spec} failed: {proc.stderr.strip().splitlines()[-1:]}")
            runs[key].append(json.loads(proc.stdout.strip().splitlines()[-1]) | {"seed": seed})
            if args.seeds > 1:
                r = runs[key][-1]
                sys.stderr.write(f"{spec} seed {seed}: {r['updates_per_s']:.1f} ups, "
                                 f"p50 {r['step_ms_p50']:.2f} ms\n")
    keys = ("updates_per_s", "step_ms_p50", "step_ms_p95", "peak_rss_mb")
    medians = {key: {k: round(float(np.median([r[k] for r in rs])), 3) for k in keys}
               for key, rs in runs.items()}
    ratio = medians["museum"]["step_ms_p50"] / medians["paper_small"]["step_ms_p50"]
    head = ["world", "seed", "ups", "p50_ms", "p95_ms", "rss_mb", "cpu_ups", "timed", "vertices"]
    rows = [head]
    for key, spec in WORLDS:
        rows += [
            [spec, str(r["seed"]), f"{r['updates_per_s']:.1f}", f"{r['step_ms_p50']:.2f}",
             f"{r['step_ms_p95']:.2f}", f"{r['peak_rss_mb']:.1f}", f"{r['cpu_updates_per_s']}",
             f"{r['first']}-{r['first'] + r['steps'] - 1}", str(r["map_vertices"])]
            for r in runs[key]
        ]
        if args.seeds > 1:
            m = medians[key]
            rows.append([spec, "median", f"{m['updates_per_s']:.1f}", f"{m['step_ms_p50']:.2f}",
                         f"{m['step_ms_p95']:.2f}", f"{m['peak_rss_mb']:.1f}", "-", "-", "-"])
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    for row in rows:
        print("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))))
    print(f"museum / paper-small median step time: {ratio:.2f}")
    summary: dict[str, Any] = {  # with one seed, the medians are that seed's figures
        "paper_small": medians["paper_small"],
        "museum": medians["museum"],
        "museum_to_small_step_ratio": round(ratio, 3),
    }
    if args.seeds > 1:
        summary["seeds"] = args.seeds
    if args.pieces:
        summary["pieces"] = pieces()
        routes = summary["pieces"].pop("plan_route_s")
        for key, value in summary["pieces"].items():
            print(f"{key:<22} {value}")
        for name, took in routes.items():
            print(f"plan_route_s {name:<9} {took}")
        summary["pieces"]["plan_route_s"] = routes
    if args.json:
        print(json.dumps(summary))
    return 0
