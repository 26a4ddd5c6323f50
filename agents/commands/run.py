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

``--sensor`` picks the robots' simulated sensor (:data:`agents.mapping_run.SENSORS`): the corner
sensor (default), the clean lidar or the realistic lidar ``lidar-real``
(:mod:`agents.sim.real_lidar`), whose scene (glass, clutter, people) is drawn from ``--seed`` and
so is the same for every robot; each robot gets ``--sensor`` and ``--scene-seed``, and
``report.json`` has ``"sensor"``.

``--secure`` runs the whole fleet authenticated and access-controlled
(:func:`agents.fleet.secure.make_secure_fleet`): fresh test certificates and passwords under
``DIR/secure/`` (private files mode 600), the router on ``tls/localhost:<free port>`` with
user/password *and* mutual TLS and the fleet ACL, and every child process given its own
``--credentials`` file (robot ``rK`` as ``rK``, the fusion service as ``fusion``; with
``--fusers K`` the root as ``fusion`` and the regional fuser of group ``gI`` as ``fuser-gI``,
which may publish only its group's partial and token, so the fusers run ``--no-standby``). It makes its
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

from agents.argtypes import add_bag_topics, non_negative_int
from agents.errors import INTERRUPTED, UserError
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
from agents.mapping_run import LIDAR_PROFILES, SENSORS
from agents.params import ConfigArgs, add_config_arguments, resolve, to_toml

MAX_ROBOTS = 64
"""``run`` starts one process per robot on this machine: at most 64 (the fused map itself takes up
to ``wire_codec.MAX_ROBOTS``, 4,096; larger fleets: ``wiremap bench fleet --synthetic``, or
robots and fusers on several machines)."""
#: Seconds the fusion service of a fleet of robots without a shared frame runs on after the
#: robots are stopped (every one done, or --duration) while some are islands: it tries
#: a pair whose maps stopped growing again after FramesConfig.retry_after_s (5 s), and an
#: attempt takes up to a fraction of a second; a join accepted then waits for its second look,
#: 5 s more once the robots' clock stopped, and a third robot's join as long again.
SETTLE_S = 20.0

HELP = "the main job: router, N robots and the fusion service"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", metavar="NAME|FILE",
                        help="built-in world name or world file (or give --carmen)")
    parser.add_argument(
        "--unknown-starts", action="store_true",
        help="each robot starts at a random pose (seeded) and publishes in its own frame: "
        "fusion registers them",
    )
    parser.add_argument("--anchor", metavar="ID", help="with unknown starts: the fleet frame is this robot's")
    parser.add_argument(
        "--carmen", metavar="LOG",
        help="split a real CARMEN log into --robots robots (overlapping stretches, each in its own frame)",
    )
    parser.add_argument(
        "--rosbag", metavar="FILE",
        help="split a ROS bag's LaserScan into --robots robots, as --carmen splits a log (ROS 1 .bag, "
        "ROS 2 bag folder or its .db3/.mcap file)",
    )
    add_bag_topics(parser, "with --rosbag: ")
    parser.add_argument("--truth-topic", metavar="TOPIC",
                        help="with --rosbag: a topic with the robot's true pose, to score the robots "
                        "and the fused map against (default: none)")
    parser.add_argument(
        "--lidar-profile", choices=tuple(LIDAR_PROFILES), default=None,
        help="with --carmen or --rosbag: the robots' real-lidar profile, lidar-slam (lidar SLAM over "
        "each robot's stretch under its filter; default) or lidar (the filter's corner ICP alone)",
    )
    parser.add_argument("--robots", required=True, type=int, metavar="N", help="number of robots (1-64)")
    parser.add_argument(
        "--duration", type=float, default=None, metavar="S",
        help="wall-clock seconds of mapping at most (default 60; with --carmen: until every robot "
        "has replayed its stretch; simulated time runs 2.5x faster at --rate 5, each scan being "
        "0.5 s of driving)",
    )
    parser.add_argument("--seed", type=non_negative_int, default=0,
                        help="random seed (routes; robot k gets seed + k)")
    parser.add_argument(
        "--sensor", choices=SENSORS, default="corners",
        help="the robots' simulated sensor: the corner sensor (default), the clean lidar or the "
        "realistic lidar (lidar-real: range noise, dropouts, glass, clutter, people; the scene "
        "is drawn from --seed, the same for every robot)",
    )
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--rate", type=float, default=5.0, metavar="HZ",
                        help="scans per second per robot (default 5)")
    parser.add_argument("--particles", type=int, default=None, help="particles per robot (default 5)")
    parser.add_argument(
        "--fusers", type=int, default=1, metavar="K",
        help="fusion processes: 1 = one service; K >= 2 = K regional fusers over the fold's subtrees "
        "and a root",
    )
    parser.add_argument(
        "--resolution", type=float, default=0.05, metavar="M",
        help="quantisation step of the robots' published maps (default 0.05)",
    )
    parser.add_argument(
        "--threshold", type=float, metavar="M",
        help="merge threshold of the robots' filters and of the fusion (default 0.2, 0.4 for worlds "
        "over 100 m)",
    )
    parser.add_argument(
        "--overlap", type=float, default=None,
        help="fraction of a route piece (or log stretch) shared with the next (default 0.15; "
        "0.3 with --carmen)",
    )
    parser.add_argument("--serve-viewer", type=int, metavar="PORT", help="serve the recording live on PORT")
    parser.add_argument("--startup-timeout", type=float, default=60.0, metavar="S", help=argparse.SUPPRESS)
    parser.add_argument("--no-progress", action="store_true", help="no live progress lines")
    parser.add_argument(
        "--stop-when-done", action="store_true",
        help="end as soon as every robot has finished its route (--duration stays the upper bound)"
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


def terminal_width(stream: Any = None) -> int:
    """Columns of the terminal ``stream`` writes to (80 when it is not a terminal)."""
    import shutil

    stream = stream or sys.stdout
    try:
        return os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, OSError, ValueError):
        return shutil.get_terminal_size((80, 24)).columns


def terminal_rows(stream: Any = None) -> int:
    stream = stream or sys.stdout
    try:
        return os.get_terminal_size(stream.fileno()).lines
    except (AttributeError, OSError, ValueError):
        return 24


def fit(line: str, width: int) -> str:
    """``line`` cut to ``width - 1`` columns (the last column left free, so that no terminal
    wraps it), with ``~`` where it was cut."""
    room = max(8, width - 1)
    return line if len(line) <= room else line[: room - 1] + "~"


#: ``--duration`` of a run that ends when its robots do (``--carmen``'s default).
OPEN_ENDED = 1e9


class Progress:
    """The live block: a clock line with the fused map, a column header and one line per robot.

    On a terminal the block is redrawn in place every 0.5 s, every line cut to the terminal's
    width (measured at each redraw) so that none wraps and the cursor-up redraw lands right;
    with more robots than rows the last line says how many are not shown. Not on a terminal
    (a pipe, a log file) the block is printed every 10 s as plain lines.
    """

    HEADER = "robot  steps  sim time  corners  walls  maps        sent"

    def __init__(self, ids: list[str], enabled: bool, stream: Any = None, t0: float = 0.0) -> None:
        self.ids = ids
        self.t0 = t0  # the robots' clock at its start (a replayed log's first stamp)
        self.enabled = enabled
        self.stream = stream or sys.stdout
        self.tty = enabled and bool(getattr(self.stream, "isatty", lambda: False)())
        self.status: dict[str, dict[str, Any]] = {}
        self.fused = ""
        self.fused_raw: bytes | None = None
        self.fused_robots: set[str] = set()  # the robots in the latest fused map
        self.tracks: dict[str, list[tuple[float, float]]] = {}
        self._drawn = 0
        self._last = 0.0

    def set_fused(self, raw: bytes, version: int, vertices: int, edges: int, robots: list[str]) -> None:
        """The latest fused map seen on the bus; its size is the payload's (what fused.wfm holds)."""
        self.fused_raw = raw
        self.fused_robots = set(robots)
        self.fused = (
            f"fused v{version}: {vertices} corners, {edges} walls, {len(raw)} bytes, from {' '.join(robots)}"
        )

    def add_pose(self, rid: str, pose: dict[str, Any]) -> None:
        """A robot's pose message: its status, and its estimated position in the fleet frame
        for the trajectory (a point every 5 cm)."""
        self.status[rid] = pose["status"]
        p = pose["fleet"]
        track = self.tracks.setdefault(rid, [])
        if not track or math.hypot(p.x - track[-1][0], p.y - track[-1][1]) >= 0.05:
            track.append((p.x, p.y))

    def line(self, rid: str) -> str:
        s = self.status.get(rid)
        if not s:
            return f"{rid:>5}  waiting"
        state = "done" if s.get("finished") else ""
        return (
            f"{rid:>5}  {s.get('step', 0):5d}  {s.get('t', self.t0) - self.t0:6.1f} s  "
            f"{s.get('vertices', 0):7d}  "
            f"{s.get('edges', 0):5d}  {s.get('maps_sent', 0):4d}  "
            f"{s.get('bytes_sent', 0) / 1024:6.1f} KiB  {state}"
        ).rstrip()

    def lines(self, elapsed: float, total: float, rows: int | None = None) -> list[str]:
        clock = f"{elapsed:5.1f} of {total:g} s" if total < OPEN_ENDED else f"{elapsed:5.1f} s"
        head = f"[{clock}] {self.fused or 'fused map: none yet'}"
        body = [self.line(r) for r in self.ids]
        if rows is not None and len(body) + 2 > rows - 1:
            keep = max(1, rows - 4)
            body = [*body[:keep], f"  ... and {len(self.ids) - keep} more robots"]
        return [head, self.HEADER, *body]

    def draw(self, elapsed: float, total: float, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        period = 0.5 if self.tty else 10.0
        if not force and now - self._last < period:
            return
        self._last = now
        out = self.stream
        if self.tty:
            width = terminal_width(out)
            lines = [fit(ln, width) for ln in self.lines(elapsed, total, terminal_rows(out))]
            if self._drawn:
                out.write(f"\x1b[{self._drawn}F")
            out.write("".join(f"\x1b[2K{ln}\n" for ln in lines))
            if self._drawn > len(lines):  # fewer lines than last time: clear the rest
                out.write("\x1b[0J")
            self._drawn = len(lines)
        else:
            out.write("\n".join(self.lines(elapsed, total)) + "\n")
        out.flush()


# ---------------------------------------------------------------------- outputs
#: Subjects of :func:`partial_note`.
ROBOT_MAP = "one robot's partial map"
FLEET_CUT_SHORT = "a fleet map cut short before every robot finished its route"
MAP_CUT_SHORT = "a map cut short"


def partial_note(subject: str = ROBOT_MAP) -> str:
    """Why ``subject`` (a partial map) has no cell error in ``report.json``."""
    return (f"not applicable to {subject}: the cell error counts unexplored area as obstacle (it "
            "would be the free share of the world it did not see); see wall_precision and "
            "mean_dist_m for what it saw, wall_recall for how much")


def _metrics(truth: Any, wf: Any, resolution: float, partial: bool = False,
             subject: str = ROBOT_MAP) -> dict[str, Any]:
    """Metrics of ``wf`` against the truth (``mapping.metrics.evaluate``). A ``partial`` map gets
    ``cell_error: null`` and ``cell_error_note`` saying why (:func:`partial_note` of
    ``subject``)."""
    from mapping.metrics import evaluate

    if wf.n_edges == 0:
        m: dict[str, Any] = {
            "cell_error": None, "wall_precision": 0.0, "wall_recall": 0.0, "mean_dist_m": None,
            "p95_dist_m": None,
        }
    else:
        m = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
             for k, v in evaluate(truth, wf, resolution).items()}
    if partial:
        m["cell_error"] = None
        m["cell_error_note"] = partial_note(subject)
    return m


def status_figures(st: dict[str, Any], t0: float = 0.0) -> dict[str, Any]:
    """A robot's figures in ``report.json``'s ``per_robot``, from its last status (0 where it
    said nothing); its clock counted from ``t0`` (a replayed log's first stamp)."""
    return {
        "bytes_sent": int(st.get("bytes_sent", 0)),
        "maps_sent": int(st.get("maps_sent", 0)),
        "steps": int(st.get("step", 0)),
        "sim_time_s": float(st["t"]) - t0 if "t" in st else 0.0,
        "finished": bool(st.get("finished", False)),  # drove its whole route
        "pose_bytes_sent": int(st.get("pose_bytes", 0)),
        "viz_bytes_sent": int(st.get("viz_bytes", 0)),
    }


def store_state(out: Path) -> dict[str, Any]:
    """The fusion store's ``state.json`` ({} when missing or unreadable)."""
    try:
        state = json.loads((out / "store" / "state.json").read_text())
    except (OSError, ValueError):
        return {}
    return state if isinstance(state, dict) else {}


def fused_from_store(out: Path, published: bytes | None = None) -> tuple[bytes, Any]:
    """The run's fused map ``(bytes, message)``: the fusion service's last published message
    (``published``, the payload seen on the bus) when it is the stored version, else the one in
    ``out/store`` (the store's copy of the same version can differ in its meta), so that
    ``fused.wfm``, the report's ``bytes`` and the live progress line agree."""
    from agents.fleet.fusion import decode_message

    store = out / "store"
    fused_path = store / "fused.wfm"
    if not fused_path.is_file():
        raise UserError(f"the fusion service left no fused map in {store} (see {out / 'logs' / 'fuse.log'})")
    raw = fused_path.read_bytes()
    msg = decode_message(raw)
    if published is not None:
        try:
            pub = decode_message(published)
        except ValueError:
            pub = None
        if pub is not None and pub.seq == msg.seq:
            return published, pub
    return raw, msg


def write_outputs(
    out: Path,
    world: Any,
    ids: list[str],
    duration_s: float,
    extra: dict[str, Any],
    published: bytes | None = None,
    tracks: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write ``fused.*`` and ``report.json`` from the fusion service's store. ``fused.wfm`` is
    the fusion service's last published message (``published``, the payload seen on the bus)
    when it is the stored version, else the stored map; its size is the ``bytes`` of the report,
    the progress line and the summary. Maps are scored on a grid of the merge threshold
    (``resolution`` in the report; ``map_resolution`` is the fused map's quantisation step)."""
    from agents.files.export import message_properties, wireframe_geojson
    from agents.files.render import map_figure
    from agents.fleet.fusion import decode_message, merge_threshold_of

    store = out / "store"
    raw, msg = fused_from_store(out, published)
    wf = msg.wireframe
    robots = list(msg.robots)
    write_atomic(out / "fused.wfm", raw)
    write_json(out / "fused.geojson", wireframe_geojson(wf, message_properties(msg, world.name)))
    for rid, xy in (tracks or {}).items():  # each robot's estimated track, fleet frame: `export --trajectory`
        rows = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        write_atomic(out / "tracks" / f"{rid}.tsv", "".join(f"{x:.4f}\t{y:.4f}\n" for x, y in rows.tolist()))
    title = f"{world.name}: fused map v{msg.seq} from {', '.join(robots) or 'no robot'}"
    write_atomic(
        out / "fused.png",
        map_figure(wf, world.truth, title=title, trajectories=tracks, free=world.free_space),
    )

    res = merge_threshold_of(msg)  # the scoring grid: the merge threshold, as the paper scores maps
    state = store_state(out)
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
            entry.update(_metrics(world.truth, rwf, res, partial=True))
            entry.update({"vertices": rwf.n_vertices, "edges": rwf.n_edges, "bytes": len(f.read_bytes())})
        else:
            entry.update(_metrics(world.truth, wf.subgraph_edges(np.zeros(wf.n_edges, bool)), res,
                                  partial=True))
            entry.update({"vertices": 0, "edges": 0, "bytes": 0})
        entry.update(status_figures(statuses.get(rid, {})))
        if rid in extra.get("cpu_s", {}):
            entry["cpu_s"] = extra["cpu_s"][rid]
        per_robot[rid] = entry
    # a fleet cut short by --duration or Ctrl-C left its map open: its cell error is no score either
    covered = all(entry.get("finished") for entry in per_robot.values())
    fused = _metrics(world.truth, wf, res, partial=not covered, subject=FLEET_CUT_SHORT)
    fused.update({"vertices": wf.n_vertices, "edges": wf.n_edges, "bytes": len(raw), "version": msg.seq})
    fused["robots"] = robots
    report = {
        "world": world.name,
        "robots": len(ids),
        "duration_s": round(duration_s, 3),
        "fused": fused,
        "per_robot": per_robot,
        "latency_ms": {"p50": lat.get("p50"), "p99": lat.get("p99"), "max": lat.get("max"),
                       "n": lat.get("n", 0)},
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
    if args.serve_viewer is not None and not 0 < args.serve_viewer < 65536:
        raise UserError(f"--serve-viewer must be a port within 1..65535, got {args.serve_viewer}")
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
        clear_previous_run(out)
        routes: list[Any] = unknown_run.prepare_carmen(out, world, ids, args)
    else:
        routes = _prepare_output(out, world, ids, args)
    robot_args = ["--particles", str(resolved.config.particles)]
    if resolved.recorded:
        write_atomic(out / "params.toml",
                     to_toml(resolved.recorded, header="filter settings of `wiremap run`'s robots"))
        robot_args += ["--params", str(out / "params.toml")]
    keys = fleet_keys(args)
    cfg, listen, creds = _router_config(args, out, keys.fleet, ids)
    child_ep = listen[0].replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")
    bus = ["--connect", child_ep, "--fleet", keys.fleet, "--parent-pid", str(os.getpid())]
    progress = Progress(ids, not args.no_progress, t0=world.t0 if args.carmen else 0.0)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    cpu: dict[str, float] = {}
    codes: dict[str, int | None] = {}
    t_start = time.monotonic()
    mapping_s = settle_s = 0.0
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
                f"wiremap run: router on {', '.join(listen)}; fleet {keys.fleet!r}; output in {out}{secure}",
                flush=True
            )
            _start_fleet(procs, args, out, ids, routes, threshold, bus, creds, robot_args)
            mapping_s = _watch_fleet(args, keys, procs, progress, sub_pose, sub_fused, stop, t_start,
                                     out / "logs")
            interrupted = stop.is_set()
            if not interrupted and (args.carmen or args.unknown_starts):
                settle_s = _settle(procs, ids, progress, sub_fused, stop, cpu, codes)
        finally:
            _stop_fleet(procs, ids, cpu, codes)
            _last_version(progress, sub_fused)
            sub_pose.undeclare()
            sub_fused.undeclare()
            router.close()
    if getattr(args, "fusers", 1) > 1:
        merge_recordings(out)
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
            **({"lidar_profile": args.lidar_profile} if args.carmen else {"sensor": args.sensor}),
            "rate_hz": args.rate,
            "particles": resolved.config.particles,
            "config_overrides": resolved.recorded,
            "interrupted": interrupted,
            "secure": bool(args.secure),
            "startup_s": round(max(0.0, time.monotonic() - t_start - mapping_s - settle_s), 2),
            "settle_s": settle_s,
        },
        published=progress.fused_raw,
        tracks={rid: np.asarray(xy) for rid, xy in progress.tracks.items()},
    )
    _print_summary(report, ids, out)
    if args.carmen or args.unknown_starts:
        isl = report.get("islands") or {}
        print(
            f"wiremap run: registered {' '.join(report.get('registered', [])) or '-'} (frame of "
            f"{report.get('fleet_root')}); islands {' '.join('+'.join(m) for m in isl.values()) or 'none'}",
            flush=True,
        )
    return INTERRUPTED if interrupted else 0


def _check_arguments(args: argparse.Namespace) -> int:
    """Refuse bad numbers before anything starts; returns the number of robots."""
    from agents.files.io import check_output_dir

    check_output_dir("--out", args.out)
    n = int(args.robots)
    if (args.scan_topic or args.odom_topic or args.truth_topic) and not args.rosbag:
        raise UserError("--scan-topic, --odom-topic and --truth-topic are for --rosbag")
    args.bag = None
    if args.rosbag:
        if args.carmen:
            raise UserError("give --carmen LOG or --rosbag FILE, not both")
        if not Path(args.rosbag).exists():
            raise UserError(f"--rosbag {args.rosbag}: no such file or folder")
        # a bag is run as a log is: args.carmen is the real log's path from here on
        args.bag = {"scan_topic": args.scan_topic, "odom_topic": args.odom_topic,
                    "truth_topic": args.truth_topic}
        args.carmen = args.rosbag
    if bool(args.world) == bool(args.carmen):
        raise UserError("give --world NAME|FILE, --carmen LOG or --rosbag FILE (one of them)")
    if args.carmen and args.bag is None and not Path(args.carmen).is_file():
        raise UserError(f"--carmen {args.carmen}: no such file")
    if not args.carmen and args.lidar_profile is not None:
        raise UserError("--lidar-profile is for --carmen and --rosbag "
                        "(a simulated world's robots use --sensor)")
    if args.lidar_profile is None:
        args.lidar_profile = "lidar-slam"
    if args.carmen and args.sensor != "corners":
        raise UserError("--sensor is for a simulated world; --carmen and --rosbag replay the log's own lidar")
    if args.anchor is not None and args.anchor not in [f"r{k + 1}" for k in range(max(0, n))]:
        raise UserError(f"--anchor must be one of the robot ids r1..r{n}, got {args.anchor!r}")
    if args.overlap is None:
        args.overlap = 0.3 if args.carmen else 0.15
    if args.carmen:
        args.stop_when_done = True
    if args.duration is None:
        args.duration = OPEN_ENDED if args.carmen else 60.0
    if args.particles is not None and args.particles < 1:
        raise UserError(f"--particles must be >= 1, got {args.particles}")
    if not 1 <= n <= MAX_ROBOTS:
        raise UserError(f"--robots must be between 1 and {MAX_ROBOTS}, got {n}")
    if not 1 <= args.fusers <= n:
        raise UserError(f"--fusers must be between 1 and the number of robots ({n}), got {args.fusers}")
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
    clear_previous_run(out)
    for rid, r in zip(ids, routes):
        write_json(out / "routes" / f"{rid}.json", {"route": np.round(r, 9).tolist()})
    return list(routes)


#: What ``wiremap run`` writes into its output directory; a new run removes all of it first.
RUN_FILES = ("fused.wfm", "fused.geojson", "fused.png", "report.json", "recording.rrd", "params.toml")
RUN_DIRS = ("store", "logs", "status", "routes", "secure", "tracks")


def merge_recordings(out: Path) -> None:
    """A fusion tree's recording: the fusers' parts (``store-g*/recording.rrd``,
    ``store/recording-root.rrd``, one recording id) merged into ``recording.rrd`` with ``rerun
    rrd merge``; the parts are removed once merged (kept, with one line, when it fails)."""
    from agents.commands.replay import find_rerun

    parts = sorted(out.glob("store-g*/recording.rrd")) + sorted(out.glob("store/recording-root.rrd"))
    parts = [p for p in parts if p.is_file() and p.stat().st_size > 0]
    exe = find_rerun()
    if not parts:
        return
    if exe is None:
        print(f"wiremap run: no rerun executable to merge the recording's parts: {len(parts)} kept",
              flush=True)
        return
    tmp = out / "recording.rrd.tmp"
    res = subprocess.run([exe, "rrd", "merge", *map(str, parts), "-o", str(tmp)],
                         capture_output=True, text=True, timeout=300)
    if res.returncode != 0 or not tmp.is_file():
        tail = (res.stderr or res.stdout).strip().splitlines()[-1:] or ["no output"]
        print(f"wiremap run: merging the recording's parts failed ({tail[0]}): kept in store*/", flush=True)
        tmp.unlink(missing_ok=True)
        return
    os.replace(tmp, out / "recording.rrd")
    for p in parts:
        p.unlink(missing_ok=True)


def clear_previous_run(out: Path) -> None:
    """Remove what an earlier run left in ``out`` (its outputs, logs, routes, statuses,
    credentials and fusion store: a new run does not resume, and no file of the old fleet stays
    beside the new ones). Other files in ``out`` are left alone."""
    import shutil

    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)
    for d in [*(out / name for name in RUN_DIRS), *out.glob("store-g*")]:  # store-gK: a tree's fusers
        if d.is_dir() and not d.is_symlink():
            shutil.rmtree(d)


def _router_config(
    args: argparse.Namespace, out: Path, fleet: str, ids: list[str]
) -> tuple[Any, list[str], dict[str, Path]]:
    """The embedded router's configuration, its listen endpoints and each child's credentials
    file (none without ``--secure``)."""
    if not args.secure:
        listen = list(args.listen) or [tcp_endpoint(free_port())]
        return config_from_args(argparse.Namespace(**{**vars(args), "listen": listen}), "router"), listen, {}
    from agents.fleet.secure import make_secure_fleet, to_zenoh_config

    given = [f for f, v in (("--config", args.config), ("--listen", args.listen),
                            ("--connect", args.connect)) if v]
    if given:
        raise UserError(f"--secure makes its own router configuration: drop {', '.join(given)}")
    if args.credentials:
        raise UserError("--secure writes the credentials itself: drop --credentials")
    listen = [f"tls/localhost:{free_port()}"]  # the generated server certificate is for localhost
    fl = make_secure_fleet(out / "secure", fleet, ids, listen=listen[0], fusers=_group_names(args, ids))
    return to_zenoh_config(fl.router), listen, dict(fl.credentials)


def _group_names(args: argparse.Namespace, ids: list[str]) -> list[str]:
    """The regional fusers' group names of ``--fusers K`` (none for one fusion service)."""
    if getattr(args, "fusers", 1) <= 1:
        return []
    from agents.fleet.fusion.tree import fold_ranges

    return [f"g{g}" for g in range(len(fold_ranges(ids, args.fusers)))]


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
    fuse_argv = ["fuse", *bus, *cred_args("fusion"), "--store", str(store), "--rrd",
                 str(out / "recording.rrd")]
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
        # (ranges of ids, not lists: a robot that joins later lands in exactly one group)
        from agents.fleet.fusion.tree import fold_ranges

        ranges = fold_ranges(ids, args.fusers)
        names = [f"g{g}" for g in range(len(ranges))]
        # every fuser records its part into one recording (same id; merged into recording.rrd
        # at the end, merge_recordings): a regional fuser its robots and its partial, the root
        # the fused map and the world
        rec_id = fuse_argv[fuse_argv.index("--recording-id") + 1]
        from agents.fleet.secure import fuser_identity

        for name, pattern in zip(names, ranges):
            # secure: each regional fuser has its own identity, which may publish its group's
            # partial only, so it cannot take another group over (no standby)
            who = fuser_identity(name)
            standby = ["--no-standby"] if who in creds else []
            argv = ["fuse", *bus, *cred_args(who), *standby, "--group", name, "--robots", pattern,
                    "--store", str(out / f"store-{name}"), "--threshold", repr(threshold),
                    "--rrd", str(out / f"store-{name}" / "recording.rrd"), "--recording-id", rec_id]
            procs[f"fuser-{name}"] = _spawn(f"fuser-{name}", argv, logs)
        fuse_argv = ["fuse", *bus, *cred_args("fusion"), "--of-groups", ",".join(names),
                     "--store", str(store), "--threshold", repr(threshold),
                     "--rrd", str(store / "recording-root.rrd"), "--recording-id", rec_id]
        if args.world and not args.unknown_starts:
            fuse_argv += ["--world", args.world]
        if args.serve_viewer is not None:
            fuse_argv += ["--serve-viewer", str(args.serve_viewer)]
    procs["fuse"] = _spawn("fuse", fuse_argv, logs)
    # Every robot's filter (the visibility sweep) and a log's lidar SLAM run compiled kernels:
    # compiled here once (or loaded from numba's cache), so that robots started together do
    # not each compile them (~5 s).
    from mapping.kernels import compile_kernels

    compile_kernels()
    for k, (rid, r) in enumerate(zip(ids, routes)):
        if args.carmen:
            procs[rid] = _spawn(rid,
                                _carmen_robot_argv(args, out, rid, k, r, threshold,
                                                   bus + cred_args(rid), filter_args), logs)
            continue
        s0 = start_pose_of(r)
        unknown = ["--unknown-start"] if args.unknown_starts else []
        sensor = [] if args.sensor == "corners" else ["--sensor", args.sensor, "--scene-seed", str(args.seed)]
        procs[rid] = _spawn(
            rid,
            [
                "robot", "--id", rid, "--world", args.world,
                "--start", f"{s0.x:.9f},{s0.y:.9f},{s0.theta:.9f}",
                "--route", str(out / "routes" / f"{rid}.json"),
                "--rate", str(args.rate), "--seed", str(args.seed + k + 1), *sensor,
                *filter_args,
                "--resolution", repr(float(args.resolution)), "--threshold", repr(threshold),
                "--status-file", str(out / "status" / f"{rid}.json"),
                *unknown, *bus, *cred_args(rid),
            ],
            logs,
        )


def _carmen_robot_argv(
    args: argparse.Namespace, out: Path, rid: str, k: int, stretch: Any, threshold: float, bus: list[str],
    filter_args: list[str],
) -> list[str]:
    """A robot replaying scans ``stretch = (i0, i1)`` of the log in its own frame (``filter_args``:
    its particles and settings as resolved, like a simulated robot's; ``args.particles`` is None
    unless given)."""
    i0, i1 = stretch
    source = ["--carmen", str(args.carmen)]
    if args.bag is not None:
        source = ["--rosbag", str(args.carmen)]
        for flag, key in (("--scan-topic", "scan_topic"), ("--odom-topic", "odom_topic"),
                          ("--truth-topic", "truth_topic")):
            if args.bag[key]:
                source += [flag, args.bag[key]]
    return [
        "robot", "--id", rid, *source, "--scans", f"{i0}:{i1}",
        "--rate", str(args.rate), "--seed", str(args.seed + k + 1), "--lidar-profile", args.lidar_profile,
        *filter_args,
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
    n = len(progress.ids)
    t_map: float | None = None
    done_at: float | None = None
    while not stop.is_set():
        now = time.monotonic()
        while (s := sub_pose.handler.try_recv()) is not None:
            who = keys.robot_of(str(s.key_expr))
            try:
                if who is not None and who in progress.ids:
                    progress.add_pose(who, decode_pose(s.payload.to_bytes()))
            except ValueError:
                pass
        _drain_fused(progress, sub_fused)
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
            if now - done_at >= 1.0:  # the last maps reach the fusion service (islands: _settle)
                break
        dead = [k for k, p in procs.items() if p.poll() is not None]
        if dead:
            tails = "; ".join(
                f"{k} exited with {procs[k].returncode} (see {logs / (k + '.log')})" for k in dead
            )
            raise UserError(f"a fleet process stopped early: {tails}")
        stop.wait(0.1)
    mapping_s = 0.0 if t_map is None else time.monotonic() - t_map
    progress.draw(mapping_s, args.duration, force=True)
    return mapping_s


def _drain_fused(progress: Progress, sub_fused: Any) -> None:
    """Every fused map received since the last call into ``progress`` (invalid ones skipped)."""
    from agents.fleet import validate

    while (s := sub_fused.handler.try_recv()) is not None:
        try:
            raw = s.payload.to_bytes()
            m = validate.fused_map(raw)
            progress.set_fused(raw, m.seq, m.wireframe.n_vertices, m.wireframe.n_edges, list(m.robots))
        except ValueError:
            pass


def _settle(
    procs: dict[str, subprocess.Popen[bytes]], ids: list[str], progress: Progress, sub_fused: Any,
    stop: Any, cpu: dict[str, float], codes: dict[str, int | None],
) -> float:
    """Mapping over (``--duration`` reached, or every robot done) with islands left (robots
    without a shared frame): the robots stop, and the fusion service gets up to
    :data:`SETTLE_S` for what waited on them (a pending join's second look, the last word of
    maps that stopped growing) before the fleet stops. A join made then is in the fused map the
    run reports. Returns the seconds it took (not counted as mapping)."""
    if set(ids) <= progress.fused_robots:
        return 0.0
    t0 = time.monotonic()
    _stop_robots(procs, ids, cpu, codes)
    left = len(set(ids) - progress.fused_robots)
    print(f"wiremap run: robots stopped, {left} not in the fleet frame; the fusion service settles "
          f"(up to {SETTLE_S:.0f} s)", flush=True)
    deadline = time.monotonic() + SETTLE_S
    while not stop.is_set() and time.monotonic() < deadline:
        _drain_fused(progress, sub_fused)
        if set(ids) <= progress.fused_robots:
            break
        stop.wait(0.2)
    return round(time.monotonic() - t0, 2)


def _last_version(progress: Progress, sub_fused: Any) -> None:
    """After the fleet stopped: a fused map of a newer version published while stopping
    replaces the last one seen. Re-publications of the same version (the stale list changes as
    the robots exit) do not: the map's size is that of the version as the fleet had it."""
    from agents.fleet.fusion import decode_message

    seen = None
    if progress.fused_raw is not None:
        try:
            seen = decode_message(progress.fused_raw).seq
        except ValueError:
            seen = None
    while (smp := sub_fused.handler.try_recv()) is not None:
        raw = smp.payload.to_bytes()
        try:
            v = decode_message(raw).seq
        except ValueError:
            continue
        if seen is None or v > seen:
            progress.fused_raw, seen = raw, v


def _record_cpu(procs: dict[str, subprocess.Popen[bytes]], names: list[str], cpu: dict[str, float]) -> None:
    for name in names:
        c = cpu_seconds(procs[name].pid)
        if c is not None:
            cpu[name] = round(c, 2)


def _stop_robots(
    procs: dict[str, subprocess.Popen[bytes]], ids: list[str], cpu: dict[str, float],
    codes: dict[str, int | None],
) -> None:
    """Record the CPU time of the robots not stopped yet into ``cpu``, then stop them (exit
    codes into ``codes``)."""
    up = [r for r in ids if r in procs and r not in codes]
    _record_cpu(procs, up, cpu)
    if up:
        codes.update(stop_processes(procs, up, 15.0))


def _stop_fleet(
    procs: dict[str, subprocess.Popen[bytes]],
    ids: list[str],
    cpu: dict[str, float],
    codes: dict[str, int | None],
) -> None:
    """Record each process's CPU time into ``cpu``, then stop the robots (those :func:`_settle`
    has not stopped) and after them the fusion service (which saves its store and closes the
    recording); exit codes into ``codes``."""
    _record_cpu(procs, [k for k in procs if k not in ids], cpu)
    _stop_robots(procs, ids, cpu, codes)
    regional = [k for k in procs if k.startswith("fuser-")]
    if regional:  # the fusion tree: the regional fusers' final partials reach the root first
        codes.update(stop_processes(procs, regional, 60.0))
        time.sleep(0.5)
    if "fuse" in procs:
        codes.update(stop_processes(procs, ["fuse"], 60.0))


def _print_summary(report: dict[str, Any], ids: list[str], out: Path) -> None:
    """The closing lines (under 80 columns): the fused map, its quality and latency, a table of
    the robots, the files. The same figures are in ``report.json``; a figure a kind of run does
    not report (a fleet of unknown starts, a CARMEN fleet) shows as ``n/a``."""
    f = report.get("fused") or {}
    lat = report.get("latency_ms") or {}
    per_robot = report.get("per_robot") or {}
    why = "interrupted" if report.get("interrupted") else (
        "every robot finished its route" if all(r.get("finished") for r in per_robot.values())
        else "--duration reached")
    lines = [
        f"wiremap run: {report.get('duration_s', 0.0):.1f} s of mapping ({why})",
        f"  fused map   v{f.get('version', 'n/a')}: {f.get('vertices', 'n/a')} corners, "
        f"{f.get('edges', 'n/a')} walls, {f.get('bytes', 'n/a')} bytes",
        f"  vs truth    wall recall {_num(f.get('wall_recall'), '.3f')}, "
        f"precision {_num(f.get('wall_precision'), '.3f')}, "
        f"cell error {_num(f.get('cell_error'), '.2%')}",
        f"  latency     p50 {_ms(lat.get('p50'))}, p99 {_ms(lat.get('p99'))} (robot publish to fused map)",
        "  robot  steps  sim time  recall  precision  maps  bytes sent",
    ]
    for rid in ids:
        r = per_robot.get(rid) or {}
        lines.append(
            f"  {rid:>5}  {_num(r.get('steps'), '5d')}  {_num(r.get('sim_time_s'), '6.1f')} s  "
            f"{_num(r.get('wall_recall'), '6.3f')}  {_num(r.get('wall_precision'), '9.3f')}  "
            f"{_num(r.get('maps_sent'), '4d')}  {_num(r.get('bytes_sent'), '10,d')}"
        )
    lines.append(f"  wrote       in {out}: fused.geojson fused.wfm fused.png")
    lines.append("              recording.rrd report.json")
    print("\n".join(lines), flush=True)


def _num(v: object, spec: str) -> str:
    """A figure for the summary (an integer spec takes the value as an integer), or "n/a" when
    there is none (or it is NaN), right-aligned in the spec's width like the figure."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (isinstance(v, float) and math.isnan(v)):
        width = len(spec) - len(spec.lstrip("0123456789"))
        return "n/a".rjust(int(spec[:width]) if width else 0)
    return format(int(v), spec) if spec.endswith("d") else format(float(v), spec)


def _ms(v: object) -> str:
    """A latency for the summary line: one decimal, or "n/a" when there was none."""
    return f"{float(v):.1f} ms" if isinstance(v, (int, float)) else "n/a"
