"""``wiremap map``: run one robot (a simulated world or a CARMEN log) and write its map.

Writes, in ``--out DIR``:

* ``map.geojson`` -- the best particle's wireframe (properties: source, steps, seed, ...);
* ``trajectory.tsv`` -- one line per scan, ``t x y theta`` of the estimated pose (``t`` is the
  simulation time, or the log's timestamp of the scan);
* ``map.png`` -- the map over the truth (when there is one) with the estimated trajectory;
* ``report.json`` -- metrics against the truth (when there is one), storage, steps, time.

A live progress line on stderr shows the step, the best map's size and the update rate (cut
to the terminal's width; not on a terminal, one line every 10 s). Ctrl-C stops the mapping,
writes the files for the steps done (``"interrupted": true`` in the report) and exits 130.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.errors import INTERRUPTED, UserError

HELP = "run one robot (simulated or a CARMEN log) and write its map"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--world", metavar="NAME|FILE", help="a built-in world name or a world GeoJSON file")
    src.add_argument("--carmen", metavar="LOG", help="a CARMEN log (FLASER lines) to map")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--sensor", choices=("corners", "lidar"), default="corners",
                        help="simulated sensor: the corner sensor or a lidar + split-and-merge (default corners)")
    parser.add_argument("--particles", type=int, default=10, help="number of particles (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--merge-threshold", type=float, default=None, metavar="M",
                        help="merge threshold in metres (default 0.2, or 0.4 for worlds over 100 m)")
    parser.add_argument("--max-range", type=float, default=None, metavar="M",
                        help="sensing range in metres (default 8 in simulation; CARMEN: the log's, at most 20)")
    parser.add_argument("--steps", type=int, default=None, metavar="N", help="stop after N scans")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S simulated seconds (the simulation does not wait for the clock)")
    parser.add_argument("--quiet", action="store_true", help="no progress line")


class Progress:
    """A live one-line progress display on stderr (at most ~10 updates per second)."""

    def __init__(self, enabled: bool, stream: Any = None) -> None:
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self._last = 0.0
        self._logged = -math.inf
        self._width = 0

    def update(self, k: int, total: int | None, vertices: int, edges: int, ups: float, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < 0.1:
            return
        self._last = now
        of = f" of {total}" if total else ""
        line = f"step {k}{of}  {vertices} corners  {edges} walls  {ups:.1f} scans/s"
        if getattr(self.stream, "isatty", lambda: False)():
            from agents.commands.run import fit, terminal_width

            line = fit(line, terminal_width(self.stream))
            self.stream.write("\r\x1b[2K" + line)
        else:  # a log file: one line now and then, not a carriage-return storm
            if not force and now - self._logged < 10.0:
                return
            self._logged = now
            self.stream.write(line + "\n")
        self._width = len(line)
        self.stream.flush()

    def close(self) -> None:
        """End the progress line, so that what follows starts on a line of its own."""
        if self.enabled and self._width and getattr(self.stream, "isatty", lambda: False)():
            self.stream.write("\n")
            self.stream.flush()
        self._width = 0


def _check(args: argparse.Namespace) -> None:
    from agents.files.io import check_output_dir

    check_output_dir("--out", args.out)
    if args.carmen is not None and not Path(args.carmen).is_file():
        raise UserError(f"--carmen {args.carmen}: no such file")
    if args.particles < 1:
        raise UserError(f"--particles must be >= 1, got {args.particles}")
    if args.steps is not None and args.steps < 1:
        raise UserError(f"--steps must be >= 1, got {args.steps}")
    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0, got {args.duration}")
    if args.merge_threshold is not None and not (math.isfinite(args.merge_threshold) and args.merge_threshold > 0):
        raise UserError(f"--merge-threshold must be a positive number of metres, got {args.merge_threshold}")
    if args.max_range is not None and not (math.isfinite(args.max_range) and args.max_range > 0):
        raise UserError(f"--max-range must be a positive number of metres, got {args.max_range}")


def write_outputs(
    out: Path,
    best: Any,
    trajectory: list[tuple[float, float, float, float]],
    report: dict[str, Any],
    truth: Any = None,
    properties: dict[str, Any] | None = None,
    title: str = "map",
    free: Any = None,
) -> None:
    """Write ``map.geojson``, ``trajectory.tsv``, ``map.png`` and ``report.json`` atomically."""
    from agents.files.io import save_wireframe_geojson, write_atomic, write_json
    from agents.files.render import map_figure

    out.mkdir(parents=True, exist_ok=True)
    save_wireframe_geojson(out / "map.geojson", best, properties)
    lines = [f"{t:.6f}\t{x:.6f}\t{y:.6f}\t{th:.6f}\n" for t, x, y, th in trajectory]
    write_atomic(out / "trajectory.tsv", "".join(lines))
    xy = np.array([(x, y) for _, x, y, _ in trajectory], dtype=np.float64).reshape(-1, 2)
    tracks = {"estimated path": xy} if len(xy) else None
    write_atomic(out / "map.png", map_figure(best, truth, title=title, trajectories=tracks, free=free))
    write_json(out / "report.json", report)


def run(args: argparse.Namespace) -> int:
    from agents import mapping_run as mr
    from mapping.filter import WireframeFilter

    _check(args)
    out = Path(args.out)
    truth = None
    world_name = None
    free = None
    if args.world is not None:
        from agents.sim.world import load_world

        world = load_world(args.world)
        truth = world.truth
        world_name = world.name
        free = world.free_space
        thr = args.merge_threshold if args.merge_threshold is not None else mr.default_merge_threshold(world)
        options = mr.SimOptions(
            sensor=args.sensor,
            max_range=args.max_range if args.max_range is not None else 8.0,
            steps=args.steps,
            duration=args.duration,
        )
        try:
            total: int | None = mr.count_sim_steps(world, options, args.seed)
            filt, inputs = mr.sim_filter(world, options, args.seed, args.particles, thr)
        except ValueError as exc:
            raise UserError(f"{args.world}: {exc}") from None
        source: dict[str, Any] = {"world": world_name, "sensor": args.sensor}
    else:
        from agents.files.carmen import read_carmen

        scans = read_carmen(args.carmen)  # CarmenError (a UserError) names the bad line
        if not scans:
            raise UserError(f"{args.carmen}: no laser scans in the log")
        thr = args.merge_threshold if args.merge_threshold is not None else 0.2
        max_range = min(float(scans[0].max_range), args.max_range if args.max_range is not None else 20.0)
        inputs = mr.carmen_inputs(scans, max_range=max_range, steps=args.steps)
        cfg = mr.filter_config_for(args.particles, thr, max_range, fov=mr.scan_fov(scans[0].angles))
        filt = WireframeFilter(cfg, mr.seeds_for(args.seed)["filter"], initial_pose=scans[0].odom)
        total = len(scans) if args.steps is None else min(len(scans), args.steps)
        source = {"carmen": str(args.carmen), "sensor": "lidar"}

    progress = Progress(not args.quiet)
    trajectory: list[tuple[float, float, float, float]] = []
    pose_err: list[float] = []
    busy = 0.0
    t_start = time.perf_counter()
    k = 0
    interrupted = False
    try:
        for st in mr.run_filter(inputs, filt, total):
            k = st.index + 1
            busy += st.step_s
            p = st.pose
            trajectory.append((st.t, p.x, p.y, p.theta))
            if st.true_pose is not None:
                pose_err.append(p.distance(st.true_pose))
            best = filt.best
            progress.update(k, total, best.n_vertices, best.n_edges, k / busy if busy > 0 else 0.0)
    except ValueError as exc:  # a malformed log line surfaces here
        progress.close()
        raise UserError(str(exc)) from None
    except KeyboardInterrupt:  # Ctrl-C: write the map as it stands (exit INTERRUPTED)
        interrupted = True
    best = filt.best
    progress.update(k, total, best.n_vertices, best.n_edges, k / busy if busy > 0 else 0.0, force=True)
    progress.close()
    wall = time.perf_counter() - t_start
    if interrupted:
        print(f"wiremap map: interrupted after {k} steps; writing the map as it stands", file=sys.stderr, flush=True)

    report: dict[str, Any] = {
        **source,
        "seed": args.seed,
        "particles": args.particles,
        "merge_threshold": thr,
        "steps": k,
        "time_s": round(wall, 3),
        "filter_time_s": round(busy, 3),
        "updates_per_s": round(k / busy, 2) if busy > 0 else None,
        "particle_bytes": filt.memory_bytes(),
        "best_bytes": best.paper_storage_bytes(),
        "vertices": best.n_vertices,
        "edges": best.n_edges,
        "metrics": None,
        "interrupted": interrupted,
    }
    if truth is not None:
        from mapping.metrics import evaluate

        metrics = evaluate(truth, best, thr) if best.n_edges else None
        report["metrics"] = None if metrics is None else {k2: _num(v) for k2, v in metrics.items()}
        if interrupted and report["metrics"] is not None:  # an unfinished map is partial
            from agents.commands.run import PARTIAL_CELL_ERROR

            report["metrics"]["cell_error"] = None
            report["metrics"]["cell_error_note"] = PARTIAL_CELL_ERROR.replace("one robot's partial map", "a map cut short")
        report["pose_error_mean_m"] = round(float(np.mean(pose_err)), 4) if pose_err else None
        report["pose_error_max_m"] = round(float(np.max(pose_err)), 4) if pose_err else None
    props = {**source, "steps": k, "seed": args.seed, "particles": args.particles, "merge_threshold": thr}
    title = f"{world_name or Path(args.carmen).name}: one robot, {k} steps, {args.particles} particles"
    write_outputs(out, best, trajectory, report, truth=truth, properties=props, title=title,
                  free=free)
    _print_summary(report, out)
    return INTERRUPTED if interrupted else 0


def _print_summary(report: dict[str, Any], out: Path) -> None:
    """Aligned closing lines (the same figures as ``report.json``)."""
    m = report.get("metrics")
    ups = report.get("updates_per_s")
    lines = [
        f"wiremap map: {report['steps']} steps in {report['time_s']:.1f} s"
        + (f" ({ups:.1f} scans/s)" if ups else "") + (", interrupted" if report.get("interrupted") else ""),
        f"  map         {report['vertices']} corners, {report['edges']} walls",
    ]
    if m:
        lines.append(
            f"  vs truth    cell error {_pct(m['cell_error'])}, wall precision {m['wall_precision']:.3f}, "
            f"recall {m['wall_recall']:.3f}"
        )
    if report.get("pose_error_mean_m") is not None:
        lines.append(f"  pose error  mean {report['pose_error_mean_m']:.3f} m, max {report['pose_error_max_m']:.3f} m")
    lines.append(f"  wrote       in {out}: map.geojson map.png trajectory.tsv report.json")
    print("\n".join(lines), flush=True)


def _pct(v: Any) -> str:
    return "n/a (map cut short)" if v is None else f"{float(v):.2%}"


def _num(v: Any) -> Any:
    f = float(v)
    return None if math.isnan(f) else round(f, 6)
