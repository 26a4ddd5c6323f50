"""``wiremap run --world NAME|FILE --robots N [--duration S] [--seed S] --out DIR``: the main job.

Starts an embedded Zenoh router (in this process, on a free loopback port unless ``--listen``
says otherwise), the fusion service and N robot processes whose routes share the world's
coverage (:func:`agents.sim.route.plan_routes`: one coverage tour cut into N consecutive pieces,
``--overlap`` of a piece shared with the next so that neighbours see common walls; each robot
starts at its piece's first point facing along it). Shows one live line per robot; after
``--duration`` seconds of mapping (or on Ctrl-C/SIGTERM, or with ``--stop-when-done`` once every
robot has finished its route) stops the robots, then the fusion
service (which saves its state and closes the recording), and writes to DIR:

* ``fused.geojson``: the fused map (the foundation GeoJSON; each wall also lists its
  contributing ``robots``);
* ``fused.wfm``: the same map in the wire codec (the fusion service's last message);
* ``fused.png``: the fused map over the ground truth;
* ``recording.rrd``: the Rerun recording (``wiremap replay DIR/recording.rrd``);
* ``report.json``: metrics of the fused map and of each robot's map against the truth, bytes
  sent per robot, publish-to-fused latency p50/p99, CPU time per process;
* ``routes/``, ``logs/``, ``store/``: the routes given to the robots, every process's output,
  the fusion service's state;
* ``params.toml``: with ``--params``/``--set``, the filter settings they changed (as applied),
  which every robot is started with (``--params``); ``report.json`` has them as
  ``config_overrides``.

``--params FILE`` and ``--set group.key=value`` (:mod:`agents.params`) set the robots' filter
settings; ``--particles`` and ``--threshold`` are shorthands for ``--set particles=`` and ``--set
merge_threshold=``, and the fusion service merges at the merge threshold in effect. They are
checked before the router or any robot starts.

The mapping clock starts when every robot has reported its first pose (process start-up is not
counted), bounded by ``--startup-timeout``.

``--secure`` runs the whole fleet authenticated and access-controlled
(:func:`agents.fleet.secure.make_secure_fleet`): fresh test certificates and passwords under
``DIR/secure/`` (private files mode 600), the router on ``tls/localhost:<free port>`` with
user/password *and* mutual TLS and the fleet ACL, and every child process given its own
``--credentials`` file (robot ``rK`` as ``rK``, the fusion service as ``fusion``). It makes its
own router configuration, so it refuses ``--config``, ``--listen`` and ``--connect``. It needs
the ``openssl`` command.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from agents.errors import UserError
from agents.files.io import write_atomic, write_json
from agents.fleet.bus import (
    StopFlag,
    add_bus_arguments,
    config_from_args,
    decode_pose,
    fleet_keys,
    free_port,
    open_session,
    tcp_endpoint,
)
from agents.fleet.proc import cpu_seconds, stop_processes
from agents.params import ConfigArgs, add_config_arguments, resolve, to_toml
from wire_codec import MAX_ROBOTS

HELP = "the main job: router, N robots and the fusion service"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", metavar="NAME|FILE", help="built-in world name or world file (or give --carmen)")
    parser.add_argument(
        "--unknown-starts", action="store_true",
        help="each robot starts at a random pose (seeded) and publishes in its own frame: fusion registers them",
    )
    parser.add_argument("--anchor", metavar="ID", help="with unknown starts: the fleet frame is this robot's")
    parser.add_argument(
        "--carmen", metavar="LOG",
        help="split a real CARMEN log into --robots robots (overlapping stretches, each in its own frame)",
    )
    parser.add_argument("--robots", required=True, type=int, metavar="N", help="number of robots (1-64)")
    parser.add_argument(
        "--duration", type=float, default=None, metavar="S",
        help="seconds of mapping (default 60; with --carmen: until every robot has replayed its stretch)",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed (routes; robot k gets seed + k)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--rate", type=float, default=5.0, metavar="HZ", help="scans per second per robot (default 5)")
    parser.add_argument("--particles", type=int, default=None, help="particles per robot (default 5)")
    parser.add_argument(
        "--fusers", type=int, default=1, metavar="K",
        help="fusion processes: 1 = one service; K >= 2 = K regional fusers over the fold's subtrees and a root",
    )
    parser.add_argument(
        "--resolution", type=float, default=0.05, metavar="M",
        help="quantisation step of the robots' published maps (default 0.05)",
    )
    parser.add_argument(
        "--threshold", type=float, metavar="M",
        help="merge threshold of the robots' filters and of the fusion (default 0.2, 0.4 for worlds over 100 m)",
    )
    parser.add_argument(
        "--overlap", type=float, default=None,
        help="fraction of a route piece (or log stretch) shared with the next (default 0.15; 0.3 with --carmen)",
    )
    parser.add_argument("--serve-viewer", type=int, metavar="PORT", help="serve the recording live on PORT")
    parser.add_argument("--startup-timeout", type=float, default=60.0, metavar="S", help=argparse.SUPPRESS)
    parser.add_argument("--no-progress", action="store_true", help="no live progress lines")
    parser.add_argument(
        "--stop-when-done", action="store_true", help="end as soon as every robot has finished its route"
    )
    parser.add_argument(
        "--secure",
        action="store_true",
        help="authenticated fleet: TLS + passwords + access control, credentials generated in DIR/secure",
    )
    add_config_arguments(parser, "--particles, --threshold")
    add_bus_arguments(parser, router=True)


# ---------------------------------------------------------------------- processes
def _spawn(name: str, argv: list[str], logs: Path) -> subprocess.Popen[bytes]:
    logs.mkdir(parents=True, exist_ok=True)
    fh = open(logs / f"{name}.log", "wb")
    try:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # own session: a terminal's Ctrl-C reaches only `run`, which stops the fleet in order
        return subprocess.Popen(
            [sys.executable, "-m", "agents", *argv],
            stdout=fh,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
    finally:
        fh.close()  # the child has its own descriptor


class Progress:
    """One live line per robot (and one for the fused map)."""

    def __init__(self, ids: list[str], enabled: bool) -> None:
        self.ids = ids
        self.enabled = enabled
        self.tty = enabled and sys.stdout.isatty()
        self.status: dict[str, dict[str, Any]] = {}
        self.fused = ""
        self._drawn = 0
        self._last = 0.0

    def line(self, rid: str) -> str:
        s = self.status.get(rid)
        if not s:
            return f"{rid:>4}  waiting"
        done = "  done" if s.get("finished") else ""
        return (
            f"{rid:>4}  step {s.get('step', 0):5d}  t {s.get('t', 0.0):6.1f}s  "
            f"vertices {s.get('vertices', 0):4d}  edges {s.get('edges', 0):4d}  "
            f"maps sent {s.get('maps_sent', 0):5d}  {s.get('bytes_sent', 0) / 1024:7.1f} KiB{done}"
        )

    def draw(self, elapsed: float, total: float, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        period = 0.5 if self.tty else 10.0
        if not force and now - self._last < period:
            return
        self._last = now
        lines = [f"[{elapsed:5.1f}/{total:.0f} s] {self.fused or 'fused map: none yet'}"]
        lines += [self.line(r) for r in self.ids]
        if self.tty:
            if self._drawn:
                sys.stdout.write(f"\x1b[{self._drawn}F")
            sys.stdout.write("".join(f"\x1b[2K{ln}\n" for ln in lines))
            self._drawn = len(lines)
        else:
            sys.stdout.write("\n".join(lines) + "\n")
        sys.stdout.flush()


# ---------------------------------------------------------------------- outputs
def _metrics(truth: Any, wf: Any, resolution: float) -> dict[str, Any]:
    from mapping.metrics import evaluate

    if wf.n_edges == 0:
        return {"cell_error": None, "wall_precision": 0.0, "wall_recall": 0.0, "mean_dist_m": None, "p95_dist_m": None}
    m = evaluate(truth, wf, resolution)
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in m.items()}


def write_outputs(
    out: Path,
    world: Any,
    ids: list[str],
    duration_s: float,
    extra: dict[str, Any],
) -> dict[str, Any]:
    """Write ``fused.*`` and ``report.json`` from the fusion service's store. Maps are scored
    on a grid of the merge threshold (``resolution`` in the report; ``map_resolution`` is the
    fused map's quantisation step)."""
    from agents.files.render import map_png
    from agents.fleet.fusion import decode_message, merge_threshold_of

    store = out / "store"
    fused_path = store / "fused.wfm"
    if not fused_path.is_file():
        raise UserError(f"the fusion service left no fused map in {store} (see {out / 'logs' / 'fuse.log'})")
    raw = fused_path.read_bytes()
    msg = decode_message(raw)
    wf = msg.wireframe
    robots = list(msg.robots)
    write_atomic(out / "fused.wfm", raw)
    doc = wf.to_geojson(
        {
            "kind": "fused_map",
            "world": world.name,
            "frame": msg.frame,
            "version": msg.seq,
            "resolution": msg.resolution,
            "merge_threshold": merge_threshold_of(msg),
            "robots": robots,
        }
    )
    for f in doc["features"]:
        p = f["properties"]
        if p.get("kind") == "wall":
            mask = int(p.get("sources", 0))
            p["robots"] = [r for k, r in enumerate(robots) if (mask >> k) & 1]
    write_json(out / "fused.geojson", doc)
    write_atomic(out / "fused.png", map_png(wf, world.truth))

    res = merge_threshold_of(msg)  # the scoring grid: the merge threshold, as the paper scores maps
    state: dict[str, Any] = {}
    try:
        state = json.loads((store / "state.json").read_text())
    except (OSError, ValueError):
        pass
    lat = (state.get("stats") or {}).get("latency_ms") or {}
    per_robot: dict[str, Any] = {}
    statuses = extra.get("robot_status", {})
    for rid in ids:
        entry: dict[str, Any] = {}
        f = store / "robots" / f"{rid}.wfm"
        if not f.is_file():  # a fusion tree (--fusers K): the robot's regional fuser has it
            f = next(iter(sorted(store.parent.glob(f"store-g*/robots/{rid}.wfm"))), f)
        if f.is_file():
            m = decode_message(f.read_bytes())
            rwf = m.wireframe.transformed(m.origin)
            entry.update(_metrics(world.truth, rwf, res))
            entry.update({"vertices": rwf.n_vertices, "edges": rwf.n_edges, "bytes": len(f.read_bytes())})
        else:
            entry.update(_metrics(world.truth, wf.subgraph_edges(np.zeros(wf.n_edges, bool)), res))
            entry.update({"vertices": 0, "edges": 0, "bytes": 0})
        st = statuses.get(rid, {})
        entry["bytes_sent"] = int(st.get("bytes_sent", 0))
        entry["maps_sent"] = int(st.get("maps_sent", 0))
        entry["steps"] = int(st.get("step", 0))
        entry["sim_time_s"] = float(st.get("t", 0.0))
        entry["finished"] = bool(st.get("finished", False))  # drove its whole route
        entry["pose_bytes_sent"] = int(st.get("pose_bytes", 0))
        entry["viz_bytes_sent"] = int(st.get("viz_bytes", 0))
        if rid in extra.get("cpu_s", {}):
            entry["cpu_s"] = extra["cpu_s"][rid]
        per_robot[rid] = entry
    fused = _metrics(world.truth, wf, res)
    fused.update({"vertices": wf.n_vertices, "edges": wf.n_edges, "bytes": len(raw), "version": msg.seq})
    fused["robots"] = robots
    report = {
        "world": world.name,
        "robots": len(ids),
        "duration_s": round(duration_s, 3),
        "fused": fused,
        "per_robot": per_robot,
        "latency_ms": {"p50": lat.get("p50"), "p99": lat.get("p99"), "max": lat.get("max"), "n": lat.get("n", 0)},
        "resolution": res,
        "merge_threshold": res,
        "map_resolution": float(msg.resolution),
        "fusion": {k: v for k, v in (state.get("stats") or {}).items() if k != "latency_ms"},
    }
    report.update({k: v for k, v in extra.items() if k != "robot_status"})
    write_json(out / "report.json", report)
    return report


# ---------------------------------------------------------------------- the job
def run(args: argparse.Namespace) -> int:
    from agents.mapping_run import default_merge_threshold, filter_config_for
    from agents.sim.world import load_world

    n = _check_arguments(args)
    cargs = ConfigArgs.from_args(args)
    out = Path(args.out)
    ids = [f"r{k + 1}" for k in range(n)]
    if args.carmen:
        from agents.fleet import unknown_run

        world: Any = unknown_run.carmen_world(args)
        default_threshold = 0.2
    else:
        world = load_world(args.world)
        default_threshold = default_merge_threshold(world)
    flags = {"particles": ("--particles", args.particles), "merge_threshold": ("--threshold", args.threshold)}
    resolved = resolve(
        cargs,
        lambda ov: filter_config_for(5, default_threshold, 8.0, overrides=ov),
        {k: v for k, v in flags.items() if v[1] is not None},
    )
    threshold = resolved.config.merge_threshold
    if args.carmen:
        routes: list[Any] = unknown_run.prepare_carmen(out, world, ids, args)
        _clear_outputs(out)
    else:
        routes = _prepare_output(out, world, ids, args)
    robot_args = ["--particles", str(resolved.config.particles)]
    if resolved.recorded:
        write_atomic(out / "params.toml", to_toml(resolved.recorded, header="filter settings of `wiremap run`'s robots"))
        robot_args += ["--params", str(out / "params.toml")]
    keys = fleet_keys(args)
    cfg, listen, creds = _router_config(args, out, keys.fleet, ids)
    child_ep = listen[0].replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")
    bus = ["--connect", child_ep, "--fleet", keys.fleet, "--parent-pid", str(os.getpid())]
    progress = Progress(ids, not args.no_progress)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    cpu: dict[str, float] = {}
    codes: dict[str, int | None] = {}
    t_start = time.monotonic()
    mapping_s = 0.0
    interrupted = False
    import zenoh

    with StopFlag() as stop:
        router = open_session(cfg, wait=False)
        assert router is not None
        sub_pose = router.declare_subscriber(keys.all_poses, zenoh.handlers.RingChannel(1024))
        sub_fused = router.declare_subscriber(keys.fused_map, zenoh.handlers.RingChannel(4))
        try:
            secure = f"; secure (credentials in {out / 'secure'})" if args.secure else ""
            print(
                f"wiremap run: router on {', '.join(listen)}; fleet {keys.fleet!r}; output in {out}{secure}", flush=True
            )
            _start_fleet(procs, args, out, ids, routes, threshold, bus, creds, robot_args)
            mapping_s = _watch_fleet(args, keys, procs, progress, sub_pose, sub_fused, stop, t_start, out / "logs")
            interrupted = stop.is_set()
        finally:
            _stop_fleet(procs, ids, cpu, codes)
            sub_pose.undeclare()
            sub_fused.undeclare()
            router.close()
    if interrupted:
        print("wiremap run: interrupted; writing what the fleet has mapped so far", flush=True)
    statuses: dict[str, Any] = {}
    for rid in ids:
        try:
            statuses[rid] = json.loads((out / "status" / f"{rid}.json").read_text())
        except (OSError, ValueError):
            statuses[rid] = progress.status.get(rid, {})
    writer = write_outputs
    if args.carmen or args.unknown_starts:
        from agents.fleet import unknown_run

        writer = unknown_run.write_outputs_carmen if args.carmen else unknown_run.write_outputs_unknown
    report = writer(
        out,
        world,
        ids,
        mapping_s,
        {
            "robot_status": statuses,
            "cpu_s": cpu,
            "exit_codes": codes,
            "seed": args.seed,
            "rate_hz": args.rate,
            "particles": resolved.config.particles,
            "config_overrides": resolved.recorded,
            "interrupted": interrupted,
            "secure": bool(args.secure),
            "startup_s": round(max(0.0, time.monotonic() - t_start - mapping_s), 2),
        },
    )
    _print_summary(report, ids, out)
    if args.carmen or args.unknown_starts:
        isl = report.get("islands") or {}
        print(
            f"wiremap run: registered {' '.join(report.get('registered', [])) or '-'} (frame of "
            f"{report.get('fleet_root')}); islands {' '.join('+'.join(m) for m in isl.values()) or 'none'}",
            flush=True,
        )
    return 0


def _check_arguments(args: argparse.Namespace) -> int:
    """Refuse bad numbers before anything starts; returns the number of robots."""
    n = int(args.robots)
    if bool(args.world) == bool(args.carmen):
        raise UserError("give --world NAME|FILE or --carmen LOG (one of them)")
    if args.carmen and not Path(args.carmen).is_file():
        raise UserError(f"--carmen {args.carmen}: no such file")
    if args.anchor is not None and args.anchor not in [f"r{k + 1}" for k in range(max(0, n))]:
        raise UserError(f"--anchor must be one of the robot ids r1..r{n}, got {args.anchor!r}")
    if args.overlap is None:
        args.overlap = 0.3 if args.carmen else 0.15
    if args.carmen:
        args.stop_when_done = True
    if args.duration is None:
        args.duration = 1e9 if args.carmen else 60.0
    if not 1 <= n <= MAX_ROBOTS:
        raise UserError(f"--robots must be between 1 and {MAX_ROBOTS}, got {n}")
    for name, v in (("--duration", args.duration), ("--rate", args.rate)):
        if not (math.isfinite(v) and v > 0):
            raise UserError(f"{name} must be a positive number, got {v}")
    if not 0 <= args.overlap <= 1:
        raise UserError(f"--overlap must be within [0, 1], got {args.overlap}")
    for name, v in (("--resolution", args.resolution), ("--threshold", args.threshold)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise UserError(f"{name} must be a positive number of metres, got {v}")
    return n


def _prepare_output(out: Path, world: Any, ids: list[str], args: argparse.Namespace) -> list[Any]:
    """Make ``out``, plan and write the robots' routes (``routes/<id>.json``), and clear what an
    earlier run left there (its outputs and its fusion store: a new run does not resume)."""
    from agents.sim.route import plan_routes

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {out}: cannot create the directory: {exc.strerror or exc}") from None
    rng = np.random.default_rng(args.seed)
    try:
        if getattr(args, "unknown_starts", False):
            from agents.fleet.unknown_run import random_routes

            routes = random_routes(world, len(ids), rng)
        else:
            routes = plan_routes(world, len(ids), rng, overlap=args.overlap)
    except ValueError as exc:
        raise UserError(f"cannot plan routes in {world.name}: {exc}") from None
    for rid, r in zip(ids, routes):
        write_json(out / "routes" / f"{rid}.json", {"route": np.round(r, 9).tolist()})
    _clear_outputs(out)
    return list(routes)


def _clear_outputs(out: Path) -> None:
    """Remove what an earlier run left in ``out`` (its outputs and its fusion store)."""
    for stale in ("fused.wfm", "fused.geojson", "fused.png", "report.json", "recording.rrd", "params.toml"):
        (out / stale).unlink(missing_ok=True)
    store = out / "store"
    if store.exists():  # a new run: do not resume an old fleet's state
        import shutil

        shutil.rmtree(store)


def _router_config(
    args: argparse.Namespace, out: Path, fleet: str, ids: list[str]
) -> tuple[Any, list[str], dict[str, Path]]:
    """The embedded router's configuration, its listen endpoints and each child's credentials
    file (none without ``--secure``)."""
    if not args.secure:
        listen = list(args.listen) or [tcp_endpoint(free_port())]
        return config_from_args(argparse.Namespace(**{**vars(args), "listen": listen}), "router"), listen, {}
    from agents.fleet.secure import make_secure_fleet, to_zenoh_config

    given = [f for f, v in (("--config", args.config), ("--listen", args.listen), ("--connect", args.connect)) if v]
    if given:
        raise UserError(f"--secure makes its own router configuration: drop {', '.join(given)}")
    if args.credentials:
        raise UserError("--secure writes the credentials itself: drop --credentials")
    listen = [f"tls/localhost:{free_port()}"]  # the generated server certificate is for localhost
    fl = make_secure_fleet(out / "secure", fleet, ids, listen=listen[0])
    return to_zenoh_config(fl.router), listen, dict(fl.credentials)


def _start_fleet(
    procs: dict[str, subprocess.Popen[bytes]],
    args: argparse.Namespace,
    out: Path,
    ids: list[str],
    routes: list[Any],
    threshold: float,
    bus: list[str],
    creds: dict[str, Path],
    filter_args: list[str],
) -> None:
    """Spawn the fusion service, then the robots (their filter settings: ``filter_args``), into
    ``procs`` (filled as they start, so that a failure half-way still stops the ones already
    running)."""
    from agents.fleet.robot import start_pose_of

    def cred_args(who: str) -> list[str]:
        return ["--credentials", str(creds[who])] if who in creds else []

    logs = out / "logs"
    store = out / "store"
    fuse_argv = ["fuse", *bus, *cred_args("fusion"), "--store", str(store), "--rrd", str(out / "recording.rrd")]
    fuse_argv += ["--threshold", repr(threshold)]
    if args.world and not args.unknown_starts:  # the truth is in the world frame, the fleet's is a robot's
        fuse_argv += ["--world", args.world]
    if args.anchor:
        fuse_argv += ["--anchor", args.anchor]
    fuse_argv += ["--recording-id", str(uuid.uuid4())]
    if args.serve_viewer is not None:
        fuse_argv += ["--serve-viewer", str(args.serve_viewer)]
    if getattr(args, "fusers", 1) > 1:
        # the fusion tree (agents.fleet.fusion.regional/root): "fuse" is the root, with the store
        # this command reads; the regional fusers over the fold's subtrees, the first records
        from agents.fleet.fusion.tree import fold_groups

        groups = fold_groups(ids, args.fusers)
        names = [f"g{g}" for g in range(len(groups))]
        for g, (name, group) in enumerate(zip(names, groups)):
            argv = ["fuse", *bus, *cred_args("fusion"), "--group", name, "--robots", ",".join(group),
                    "--store", str(out / f"store-{name}"), "--threshold", repr(threshold)]
            if g == 0:
                argv += fuse_argv[fuse_argv.index("--rrd"):]
            procs[f"fuser-{name}"] = _spawn(f"fuser-{name}", argv, logs)
        fuse_argv = ["fuse", *bus, *cred_args("fusion"), "--of-groups", ",".join(names), "--store", str(store),
                     "--threshold", repr(threshold)]
    procs["fuse"] = _spawn("fuse", fuse_argv, logs)
    for k, (rid, r) in enumerate(zip(ids, routes)):
        if args.carmen:
            procs[rid] = _spawn(rid, _carmen_robot_argv(args, out, rid, k, r, threshold, bus + cred_args(rid)), logs)
            continue
        s0 = start_pose_of(r)
        unknown = ["--unknown-start"] if args.unknown_starts else []
        procs[rid] = _spawn(
            rid,
            [
                "robot", "--id", rid, "--world", args.world,
                "--start", f"{s0.x:.9f},{s0.y:.9f},{s0.theta:.9f}",
                "--route", str(out / "routes" / f"{rid}.json"),
                "--rate", str(args.rate), "--seed", str(args.seed + k + 1),
                *filter_args,
                "--resolution", repr(float(args.resolution)), "--threshold", repr(threshold),
                "--status-file", str(out / "status" / f"{rid}.json"),
                *unknown, *bus, *cred_args(rid),
            ],
            logs,
        )


def _carmen_robot_argv(
    args: argparse.Namespace, out: Path, rid: str, k: int, stretch: Any, threshold: float, bus: list[str]
) -> list[str]:
    """A robot replaying scans ``stretch = (i0, i1)`` of the log in its own frame."""
    i0, i1 = stretch
    return [
        "robot", "--id", rid, "--carmen", str(args.carmen), "--scans", f"{i0}:{i1}",
        "--rate", str(args.rate), "--seed", str(args.seed + k + 1), "--particles", str(args.particles),
        "--resolution", repr(float(args.resolution)), "--threshold", repr(threshold),
        "--status-file", str(out / "status" / f"{rid}.json"), *bus,
    ]


def _watch_fleet(
    args: argparse.Namespace,
    keys: Any,
    procs: dict[str, subprocess.Popen[bytes]],
    progress: Progress,
    sub_pose: Any,
    sub_fused: Any,
    stop: StopFlag,
    t_start: float,
    logs: Path,
) -> float:
    """The progress loop: show the robots' status and the fused map until ``--duration`` seconds
    of mapping have passed (the clock starts when every robot is up, or at the start-up
    timeout), every robot is done (``--stop-when-done``) or ``stop`` is set. Raises
    ``UserError`` when a fleet process stops early. Returns the seconds of mapping."""
    from agents.fleet import validate

    n = len(progress.ids)
    t_map: float | None = None
    done_at: float | None = None
    while not stop.is_set():
        now = time.monotonic()
        while (s := sub_pose.handler.try_recv()) is not None:
            who = keys.robot_of(str(s.key_expr))
            try:
                if who is not None and who in progress.ids:
                    progress.status[who] = decode_pose(s.payload.to_bytes())["status"]
            except ValueError:
                pass
        while (s := sub_fused.handler.try_recv()) is not None:
            try:
                m = validate.fused_map(s.payload.to_bytes())
                progress.fused = (
                    f"fused v{m.seq}: {m.wireframe.n_vertices} vertices, {m.wireframe.n_edges} edges, "
                    f"{len(s.payload.to_bytes())} bytes from {' '.join(m.robots)}"
                )
            except ValueError:
                pass
        if t_map is None and (
            len(progress.status) == n or now - t_start > args.startup_timeout
        ):
            t_map = now
        elapsed = 0.0 if t_map is None else now - t_map
        progress.draw(elapsed, args.duration)
        if t_map is not None and elapsed >= args.duration:
            break
        if args.stop_when_done and len(progress.status) == n and all(
            st.get("finished") for st in progress.status.values()
        ):
            done_at = now if done_at is None else done_at
            if now - done_at >= 1.0:  # the last maps reach the fusion service
                break
        dead = [k for k, p in procs.items() if p.poll() is not None]
        if dead:
            tails = "; ".join(f"{k} exited with {procs[k].returncode} (see {logs / (k + '.log')})" for k in dead)
            raise UserError(f"a fleet process stopped early: {tails}")
        stop.wait(0.1)
    mapping_s = 0.0 if t_map is None else time.monotonic() - t_map
    progress.draw(mapping_s, args.duration, force=True)
    return mapping_s


def _stop_fleet(
    procs: dict[str, subprocess.Popen[bytes]],
    ids: list[str],
    cpu: dict[str, float],
    codes: dict[str, int | None],
) -> None:
    """Record each process's CPU time into ``cpu``, then stop the robots and after them the
    fusion service (which saves its store and closes the recording); exit codes into ``codes``."""
    for name, p in procs.items():
        c = cpu_seconds(p.pid)
        if c is not None:
            cpu[name] = round(c, 2)
    robots_up = [r for r in ids if r in procs]
    if robots_up:
        codes.update(stop_processes(procs, robots_up, 15.0))
    regional = [k for k in procs if k.startswith("fuser-")]
    if regional:  # the fusion tree: the regional fusers' final partials reach the root first
        codes.update(stop_processes(procs, regional, 60.0))
        time.sleep(0.5)
    if "fuse" in procs:
        codes.update(stop_processes(procs, ["fuse"], 60.0))


def _print_summary(report: dict[str, Any], ids: list[str], out: Path) -> None:
    """The closing lines: the fused map's size, quality and latency, then one line per robot."""
    f = report["fused"]
    lat = report["latency_ms"]
    print(
        f"wiremap run: fused v{f['version']}: {f['vertices']} vertices, {f['edges']} edges, {f['bytes']} bytes; "
        f"wall recall {f['wall_recall']:.3f}, precision {f['wall_precision']:.3f}, cell error {f['cell_error']}; "
        f"latency p50 {_ms(lat.get('p50'))}, p99 {_ms(lat.get('p99'))}",
        flush=True,
    )
    for rid in ids:
        r = report["per_robot"][rid]
        print(
            f"  {rid}: wall recall {r['wall_recall']:.3f}, {r['maps_sent']} maps, {r['bytes_sent']} bytes sent",
            flush=True,
        )
    print(f"wiremap run: wrote {out}/fused.geojson fused.wfm fused.png recording.rrd report.json", flush=True)


def _ms(v: object) -> str:
    """A latency for the summary line: one decimal, or "n/a" when there was none."""
    return f"{float(v):.1f} ms" if isinstance(v, (int, float)) else "n/a"
