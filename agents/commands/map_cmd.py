"""``wiremap map``: run one robot (a simulated world, a CARMEN log or a ROS bag) and write its map.

Writes, in ``--out DIR``:

* ``map.geojson`` -- the best particle's wireframe (properties: source, steps, seed, ...);
* ``trajectory.tsv`` -- one line per scan, ``t x y theta`` of the estimated pose (``t`` is the
  simulation time, or the log's timestamp of the scan);
* ``map.png`` -- the map over the truth (when there is one) with the estimated trajectory;
* ``report.json`` -- metrics against the truth (when there is one), storage, steps, time.

A CARMEN log is read as it is (:func:`agents.files.carmen.read_carmen_log`): unreadable lines are
reported on stderr with their line number and skipped (``--strict``: the first one is an error).
When the log has a ``TRUEPOS`` track or a ``NAME.truth.tsv`` beside it, the filter starts at the
true first pose and the run is scored against it (:mod:`mapping.lidar_metrics`: ATE without
alignment, relative error over 1 m, map precision and coverage at 0.2 m against the real scan
endpoints placed at the true poses, and the precision after one rigid alignment of the map to
them) and ``map.png`` shows the map over those endpoints.

A ROS bag (``--rosbag``: a ROS 1 ``.bag``, a ROS 2 bag folder or its ``.db3``/``.mcap`` file) is
read by :func:`agents.files.rosbag.read_rosbag`: ``sensor_msgs/LaserScan`` from ``--scan-topic``
(default the bag's only one), odometry from ``--odom-topic`` (default the only
``nav_msgs/Odometry`` topic, else ``/tf`` between ``--odom-frame`` and ``--base-frame``), the
laser's mount from ``/tf_static``; ``--truth-topic`` names a topic with the robot's true pose to
score against. It is mapped as a CARMEN log is (the same real-lidar profile); unreadable messages
are reported and skipped like unreadable lines (``--strict``: the first one is an error).
``report.json`` says which input was mapped (``"input"``: ``world``, ``carmen`` or ``rosbag``),
and for a bag its format, the topics used, the scans and the messages skipped.

A live progress line on stderr shows the step, the best map's size and the update rate.

``--params FILE`` and ``--set group.key=value`` change the filter's settings
(:mod:`agents.params`); ``--particles``, ``--merge-threshold`` and ``--max-range`` are shorthands
for ``--set particles=``, ``merge_threshold=`` and ``max_range=`` (the sensor, or the log's
ranges, then reach as far as the filter's ``max_range``, and maps are scored at its merge
threshold). ``report.json`` records the settings from ``--params`` and ``--set`` as applied
(``config_overrides``).

The progress line is cut
to the terminal's width; not on a terminal, one line every 10 s). Ctrl-C stops the mapping,
writes the files for the steps done (``"interrupted": true`` in the report) and exits 130.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.argtypes import add_bag_topics, non_negative_int
from agents.errors import INTERRUPTED, UserError
from agents.files.rosbag import DEFAULT_BASE_FRAME, DEFAULT_ODOM_FRAME
from agents.mapping_run import LIDAR_PROFILES
from agents.params import ConfigArgs, Resolved, add_config_arguments, resolve

HELP = "run one robot (simulated, CARMEN log, ROS bag), write its map"
MAX_ISSUES_SHOWN = 5  # unreadable CARMEN lines or bag messages reported one by one on stderr
#: Flags that only a ROS bag takes (``--rosbag``).
BAG_FLAGS = ("scan_topic", "odom_topic", "odom_frame", "base_frame", "truth_topic")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--world", metavar="NAME|FILE", help="a built-in world name or a world GeoJSON file")
    src.add_argument("--carmen", metavar="LOG", help="a CARMEN log (FLASER lines) to map")
    src.add_argument("--rosbag", metavar="FILE",
                     help="a ROS bag to map: ROS 1 .bag, ROS 2 bag folder or its .db3/.mcap file")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--sensor", choices=("corners", "lidar", "lidar-real"), default="corners",
                        help="simulated sensor: the corner sensor, a lidar + split-and-merge, or the "
                             "realistic lidar (lidar-real: range noise, dropouts, glass, clutter, "
                             "people; its scene drawn from --seed) (default corners)")
    parser.add_argument("--particles", type=int, default=None, help="number of particles (default 10)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="random seed (default 0)")
    parser.add_argument("--merge-threshold", type=float, default=None, metavar="M",
                        help="merge threshold in metres (default 0.2, or 0.4 for worlds over 100 m)")
    parser.add_argument("--max-range", type=float, default=None, metavar="M",
                        help="sensing range in metres (default 8 in simulation; "
                             "CARMEN log or ROS bag: the scanner's, at most 20)")
    parser.add_argument("--steps", type=int, default=None, metavar="N",
                        help="stop after N scans (a log or bag: its first N scans, before the motion filter "
                             "thins a dense one)")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S simulated seconds (the simulation does not wait for the clock)")
    parser.add_argument("--strict", action="store_true",
                        help="CARMEN log or ROS bag: an unreadable line or message is an error "
                             "(default: skip it and count it)")
    bag = parser.add_argument_group("ROS bag (--rosbag)")
    add_bag_topics(bag)
    bag.add_argument("--odom-frame", metavar="FRAME",
                     help=f"odometry from /tf: the odometry frame (default {DEFAULT_ODOM_FRAME})")
    bag.add_argument("--base-frame", metavar="FRAME",
                     help=f"the robot's base frame, for /tf odometry and the laser's mount on /tf_static "
                          f"(default {DEFAULT_BASE_FRAME})")
    bag.add_argument("--truth-topic", metavar="TOPIC",
                     help="a topic with the robot's true pose (nav_msgs/Odometry or "
                          "geometry_msgs/PoseStamped) to start from and score against (default: none)")
    parser.add_argument("--lidar-profile", choices=tuple(LIDAR_PROFILES), default=None,
                        help="real scans (--carmen, --rosbag): lidar-slam, lidar SLAM under the filter "
                             "(default), or lidar, the filter's corner ICP alone "
                             "(agents.mapping_run.LIDAR_PROFILES)")
    parser.add_argument("--quiet", action="store_true", help="no progress line")
    add_config_arguments(parser, "--particles, --merge-threshold, --max-range")


class Progress:
    """A live one-line progress display on stderr (at most ~10 updates per second)."""

    def __init__(self, enabled: bool, stream: Any = None) -> None:
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self._last = 0.0
        self._logged = -math.inf
        self._width = 0

    def update(
        self, k: int, total: int | None, vertices: int, edges: int, ups: float, force: bool = False
    ) -> None:
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
    if args.rosbag is not None and not Path(args.rosbag).exists():
        raise UserError(f"--rosbag {args.rosbag}: no such file or directory")
    real = args.carmen is not None or args.rosbag is not None
    if real and args.sensor != "corners":
        raise UserError("--sensor is for a simulated world; a log or bag maps its own lidar")
    if real and args.duration is not None:
        raise UserError("--duration is for a simulated world; a log or bag maps to its end "
                        "(--steps N stops after N scans)")
    if not real and args.strict:
        raise UserError("--strict is for a CARMEN log or a ROS bag (--carmen, --rosbag)")
    if not real and args.lidar_profile is not None:
        raise UserError("--lidar-profile is for real scans (--carmen, --rosbag)")
    if args.lidar_profile is None:
        args.lidar_profile = "lidar-slam"
    if args.rosbag is None:
        for name in BAG_FLAGS:
            if getattr(args, name) is not None:
                raise UserError(f"--{name.replace('_', '-')} is for a ROS bag: it needs --rosbag")
    if args.particles is not None and args.particles < 1:
        raise UserError(f"--particles must be >= 1, got {args.particles}")
    if args.steps is not None and args.steps < 1:
        raise UserError(f"--steps must be >= 1, got {args.steps}")
    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0, got {args.duration}")
    if args.merge_threshold is not None and not (
        math.isfinite(args.merge_threshold) and args.merge_threshold > 0
    ):
        raise UserError(f"--merge-threshold must be a positive number of metres, got {args.merge_threshold}")
    if args.max_range is not None and not (math.isfinite(args.max_range) and args.max_range > 0):
        raise UserError(f"--max-range must be a positive number of metres, got {args.max_range}")


def _filter_config(
    args: argparse.Namespace, cargs: ConfigArgs, thr: float, max_range: float, fov: float = 2.0 * math.pi,
    range_cap: float = math.inf, base: dict[str, Any] | None = None,
) -> Resolved:
    """The filter's configuration: 10 particles, ``thr``, ``max_range`` and ``fov`` under the
    file, the flags (``--max-range`` at most ``range_cap``, a log's scanner range) and
    ``--set``; a bad key or value is a one-line :class:`UserError`."""
    from agents.mapping_run import filter_config_for

    flags = {
        "particles": ("--particles", args.particles),
        "merge_threshold": ("--merge-threshold", args.merge_threshold),
        "max_range": ("--max-range", None if args.max_range is None else min(args.max_range, range_cap)),
    }
    return resolve(
        cargs,
        lambda ov: filter_config_for(10, thr, max_range, fov, overrides={**(base or {}), **ov}),
        {k: v for k, v in flags.items() if v[1] is not None},
    )


def write_outputs(
    out: Path,
    best: Any,
    trajectory: list[tuple[float, float, float, float]],
    report: dict[str, Any],
    truth: Any = None,
    properties: dict[str, Any] | None = None,
    png: bytes | None = None,
    title: str = "map",
    free: Any = None,
) -> None:
    """Write ``map.geojson``, ``trajectory.tsv``, ``map.png`` (``png`` when given, else the map
    over ``truth``) and ``report.json`` atomically."""
    from agents.files.io import save_wireframe_geojson, write_atomic, write_json
    from agents.files.render import map_figure

    out.mkdir(parents=True, exist_ok=True)
    save_wireframe_geojson(out / "map.geojson", best, properties)
    lines = [f"{t:.6f}\t{x:.6f}\t{y:.6f}\t{th:.6f}\n" for t, x, y, th in trajectory]
    write_atomic(out / "trajectory.tsv", "".join(lines))
    xy = np.array([(x, y) for _, x, y, _ in trajectory], dtype=np.float64).reshape(-1, 2)
    if png is None:
        tracks = {"estimated path": xy} if len(xy) else None
        png = map_figure(best, truth, title=title, trajectories=tracks, free=free)
    write_atomic(out / "map.png", png)
    write_json(out / "report.json", report)


@dataclass
class _Source:
    """What one ``wiremap map`` maps: the filter and its scans, with what scores them."""

    filt: Any
    inputs: Any
    total: int | None
    source: dict[str, Any]
    resolved: Resolved
    name: str
    truth: Any = None  # the world's true walls (a simulated world)
    free: Any = None  # the world's free space (shaded outside in the picture)
    scans: Any = None  # a real log's scans, their true poses and the range mapped
    true_scans: Any = None
    max_range: float = 0.0
    extra: dict[str, Any] | None = None  # what report.json adds for this input
    route_steps: int | None = None  # a simulated route in scans (--steps, --duration may cut it)


def _world_source(args: argparse.Namespace, cargs: ConfigArgs) -> _Source:
    """A simulated robot driving its coverage route through ``--world``."""
    from agents import mapping_run as mr
    from agents.sim.world import load_world

    world = load_world(args.world)
    resolved = _filter_config(args, cargs, mr.default_merge_threshold(world), 8.0)
    cfg = resolved.config
    options = mr.SimOptions(sensor=args.sensor, max_range=cfg.max_range, steps=args.steps,
                            duration=args.duration)
    try:
        total, whole = mr.sim_step_counts(world, options, args.seed)
        filt, inputs = mr.sim_filter(world, options, args.seed, cfg.particles,
                                     cfg.merge_threshold, config=cfg)
    except ValueError as exc:
        raise UserError(f"{args.world}: {exc}") from None
    source = {"input": "world", "world": world.name, "sensor": args.sensor}
    return _Source(filt, inputs, total, source, resolved, world.name, truth=world.truth,
                   free=world.free_space, route_steps=whole)


def _log_source(args: argparse.Namespace, cargs: ConfigArgs, lidar: dict[str, Any]) -> _Source:
    """A CARMEN log (:func:`_real_source`)."""
    from agents.files.carmen import read_carmen_log, scan_truth

    # CarmenError (a UserError) names the bad line; without --strict such lines are skipped.
    log = read_carmen_log(args.carmen, strict=args.strict)
    _show_issues(log.issues, "unreadable lines")
    if not log.scans:
        raise UserError(f"{args.carmen}: no laser scans in the log")
    source = {"input": "carmen", "carmen": str(args.carmen), "sensor": "lidar", "laser": log.laser}
    return _real_source(args, cargs, lidar, log.scans, scan_truth(log), source, Path(args.carmen).name,
                        {"skipped_lines": len(log.issues)})


def _bag_source(args: argparse.Namespace, cargs: ConfigArgs, lidar: dict[str, Any]) -> _Source:
    """A ROS bag (:func:`_real_source`): its LaserScan topic, posed by its odometry."""
    from agents.files.rosbag import read_rosbag

    # RosbagError (a UserError) names the bad topic or message; without --strict such messages
    # are skipped.
    bag = read_rosbag(
        args.rosbag, scan_topic=args.scan_topic, odom_topic=args.odom_topic,
        odom_frame=args.odom_frame or DEFAULT_ODOM_FRAME, base_frame=args.base_frame or DEFAULT_BASE_FRAME,
        truth_topic=args.truth_topic, strict=args.strict,
    )  # fmt: skip
    _show_issues(bag.issues, "unreadable messages")
    if not bag.scans:
        read = bag.messages.get(bag.scan_topic, 0)
        odometry = f"{bag.odometry}: {bag.messages.get(bag.odometry, 0)} messages"
        if bag.truth_topic is not None:
            odometry += f"; truth {bag.truth_topic}: {bag.messages.get(bag.truth_topic, 0)} messages"
        raise UserError(f"{args.rosbag}: no scan to map ({bag.scan_topic}: {read} messages, "
                        f"{sum(bag.skipped.values())} unreadable, {bag.unposed} without odometry at "
                        f"their time; {odometry})")
    source = {
        "input": "rosbag",
        "rosbag": str(args.rosbag),
        "sensor": "lidar",
        "format": bag.format,
        "scan_topic": bag.scan_topic,
        "odometry": bag.odometry,
    }
    extra = {
        "odom_frames": list(bag.odom_frames) if bag.odom_frames else None,
        "truth_topic": bag.truth_topic,
        "laser_frame": bag.laser_frame,
        "mount": {"x": bag.mount.x, "y": bag.mount.y, "theta": bag.mount.theta, "from": bag.mount_from,
                  "upside_down": bag.upside_down},
        "messages": bag.messages,
        "scans": len(bag.scans),
        "skipped_messages": sum(bag.skipped.values()),
        "skipped_by_topic": bag.skipped,
        "unposed_scans": bag.unposed,
    }
    return _real_source(args, cargs, lidar, bag.scans, bag.truth, source, Path(args.rosbag).name, extra)


#: Setting groups of the real-lidar front end (``--params`` and ``--set`` with ``--carmen`` or
#: ``--rosbag``): split-and-merge (:class:`mapping.extract.ExtractConfig`), the raw points
#: (:class:`mapping.lidar_frontend.FrontendConfig`) and the lidar SLAM
#: (:class:`mapping.lidar_slam.SlamConfig`), on top of ``--lidar-profile``'s.
LIDAR_GROUPS = ("extract", "frontend", "slam")


def _split_lidar(args: argparse.Namespace, cargs: ConfigArgs) -> tuple[ConfigArgs, dict[str, Any]]:
    """``(the filter's --params and --set, the real-lidar front end's)``: the keys of
    :data:`LIDAR_GROUPS` taken out (the file's, then ``--set``'s over them) and checked against
    the profile; a bad one, or one for a simulated world, is a one-line :class:`UserError`."""
    def ours(key: str) -> bool:
        return key.partition(".")[0] in LIDAR_GROUPS

    lidar = {k: v for k, v in cargs.file_values.items() if ours(k)}
    lidar.update({k: v for k, v in cargs.set_values.items() if ours(k)})
    rest = ConfigArgs(cargs.params, {k: v for k, v in cargs.file_values.items() if not ours(k)},
                      {k: v for k, v in cargs.set_values.items() if not ours(k)})
    if lidar and args.world is not None:
        raise UserError(f"{next(iter(lidar))}: a real lidar's setting (--carmen, --rosbag), not a "
                        f"simulated world's")
    if lidar:
        _lidar_configs(args, lidar)
    return rest, lidar


def _lidar_configs(args: argparse.Namespace, lidar: dict[str, Any]) -> tuple[dict[str, Any], Any, Any]:
    """``--lidar-profile`` with ``lidar`` over it (:func:`agents.mapping_run.split_profile`)."""
    from agents import mapping_run as mr
    from mapping.config import ConfigError

    try:
        return mr.split_profile({**mr.lidar_profile(args.lidar_profile), **lidar})
    except (ConfigError, ValueError) as exc:
        raise UserError(f"--set: {exc}") from None


def _show_issues(issues: list[str], what: str) -> None:
    """The first unreadable lines or messages on stderr, then how many more."""
    for msg in issues[:MAX_ISSUES_SHOWN]:
        print(f"wiremap: skipped {msg}", file=sys.stderr)
    if len(issues) > MAX_ISSUES_SHOWN:
        print(f"wiremap: skipped {len(issues) - MAX_ISSUES_SHOWN} more {what}", file=sys.stderr)


def _real_source(
    args: argparse.Namespace, cargs: ConfigArgs, lidar: dict[str, Any], scans: list[Any],
    true_scans: list[Any] | None, source: dict[str, Any], name: str, extra: dict[str, Any],
) -> _Source:
    """Real scans (:class:`agents.files.carmen.LaserScan`) through the real-lidar profile
    (odometry noise, point match, extractor) under the user's ``--params`` and ``--set`` (the
    front end's own, ``lidar``, on the profile's); the filter starts at the true first pose when
    the scans have a truth. A dense log is thinned by the motion filter first
    (:func:`agents.mapping_run.motion_filtered`)."""
    from agents import mapping_run as mr
    from mapping.filter import WireframeFilter

    log_range = float(scans[0].max_range)
    filter_overrides, extract_cfg, frontend_cfg = _lidar_configs(args, lidar)
    resolved = _filter_config(args, cargs, 0.2, min(log_range, 20.0), mr.scan_fov(scans[0].angles),
                              log_range, base=filter_overrides)
    cfg = resolved.config
    if args.steps is not None:  # the log's first N scans, then the motion filter
        scans = scans[: args.steps]
        true_scans = None if true_scans is None else true_scans[: args.steps]
    in_log = len(scans)
    sweep = mr.judged_sweep(scans, frontend_cfg)  # the order of the beams, for the de-skew and the report
    scans, true_scans, left_out = mr.motion_filtered(scans, true_scans, frontend_cfg, sweep)
    if left_out and not args.quiet:
        print(f"wiremap: a dense log ({in_log} scans): {len(scans)} mapped, one every "
              f"{frontend_cfg.min_travel:g} m or {math.degrees(frontend_cfg.min_turn):g} degrees of the "
              f"wheels (frontend.min_travel, min_turn; frontend.dense_share=1 maps every scan)",
              file=sys.stderr)
    cal = mr.calibrate_log(scans, frontend_cfg)
    extra = {**extra, "scans_in_log": in_log, "scans_left_out": left_out,
             "lidar_profile": args.lidar_profile, "lidar_settings": dict(lidar), **mr.yaw_report(cal),
             **mr.odometry_report(cal.noise, frontend_cfg.slam), **mr.sweep_report(sweep)}

    def measured(noise: Any) -> None:  # the online SLAM measured the wheels again: report that
        extra.update(mr.odometry_report(noise, frontend_cfg.slam))

    inputs = mr.carmen_inputs(scans, max_range=cfg.max_range, truth=true_scans,
                              extract=extract_cfg, frontend=frontend_cfg, calibration=cal, on_noise=measured)
    start = true_scans[0] if true_scans is not None else scans[0].odom
    filt = WireframeFilter(cfg, mr.seeds_for(args.seed)["filter"], initial_pose=start)
    total = len(scans)
    return _Source(filt, inputs, total, source, resolved, name, scans=scans, true_scans=true_scans,
                   max_range=cfg.max_range, extra=extra)


@dataclass
class _Drive:
    """What feeding the scans to the filter left: the trajectory, the pose errors (simulated
    worlds), the filter's own time, the steps done and whether Ctrl-C cut it short."""

    trajectory: list[tuple[float, float, float, float]]
    pose_err: list[float]
    busy: float
    steps: int
    interrupted: bool
    wall: float


class _CtrlC:
    """SIGINT as a flag from the first scan until the outputs are written.

    While the scans are fed the loop checks the flag after every step. A KeyboardInterrupt
    raised wherever the signal lands can be lost: raised inside a ``__del__`` or a C library's
    callback, Python prints "Exception ignored" and goes on, and the map ran to its end (a
    flake seen under load). Setting a flag cannot be lost. A second Ctrl-C during a step raises
    KeyboardInterrupt there (a step that does not return), which the loop takes as the first.
    Once the scans stop (:attr:`writing`), Ctrl-C is only noted: the map, its report and its
    pictures are written whole, in a second or two, and the command then exits."""

    def __init__(self) -> None:
        self.hit = False
        self.writing = False
        self._old: Any = None

    def __enter__(self) -> _CtrlC:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            old = signal.getsignal(signal.SIGINT)
            if old is signal.default_int_handler:  # not when SIGINT is ignored or already taken
                self._old = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.hit and not self.writing:
            raise KeyboardInterrupt
        self.hit = True

    def __exit__(self, *exc: object) -> None:
        import signal

        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)


def _drive(src: _Source, quiet: bool, ctrl_c: _CtrlC) -> _Drive:
    """Feed every scan to the filter, with a progress line; Ctrl-C (``ctrl_c``'s flag) stops it
    after the step it lands in (what is mapped stays), a malformed log line is a
    :class:`UserError`."""
    from agents import mapping_run as mr

    filt = src.filt
    progress = Progress(not quiet)
    run = _Drive([], [], 0.0, 0, False, 0.0)
    t_start = time.perf_counter()
    try:
        for st in mr.run_filter(src.inputs, filt, src.total):
            run.steps = st.index + 1
            run.busy += st.step_s
            p = st.pose
            run.trajectory.append((st.t, p.x, p.y, p.theta))
            if st.true_pose is not None:
                run.pose_err.append(p.distance(st.true_pose))
            best = filt.best
            progress.update(run.steps, src.total, best.n_vertices, best.n_edges, _rate(run))
            if ctrl_c.hit:
                break
    except ValueError as exc:  # a malformed log line surfaces here
        progress.close()
        raise UserError(str(exc)) from None
    except KeyboardInterrupt:  # a second Ctrl-C inside a step: stop there all the same
        ctrl_c.hit = True
    ctrl_c.writing = True
    # Ctrl-C in the last step stopped nothing: the run is whole
    run.interrupted = ctrl_c.hit and (src.total is None or run.steps < src.total)
    best = filt.best
    progress.update(run.steps, src.total, best.n_vertices, best.n_edges, _rate(run), force=True)
    progress.close()
    run.wall = time.perf_counter() - t_start
    if run.interrupted:
        print(f"wiremap map: interrupted after {run.steps} steps; writing the map as it stands",
              file=sys.stderr, flush=True)
    return run


def _rate(run: _Drive) -> float:
    return run.steps / run.busy if run.busy > 0 else 0.0


def run(args: argparse.Namespace) -> int:
    _check(args)
    cargs, lidar = _split_lidar(args, ConfigArgs.from_args(args))
    _filter_config(args, cargs, 0.2, 8.0)  # the keys and values, before any work
    out = Path(args.out)
    if args.world is not None:
        src = _world_source(args, cargs)
    elif args.carmen is not None:
        src = _log_source(args, cargs, lidar)
    else:
        src = _bag_source(args, cargs, lidar)
    with _CtrlC() as ctrl_c:  # from the first scan until everything is written
        done = _drive(src, args.quiet, ctrl_c)
        _write_results(args, src, done, out)
    return INTERRUPTED if done.interrupted else 0


def _write_results(args: argparse.Namespace, src: _Source, done: _Drive, out: Path) -> None:
    """Score the map (a simulated world's truth, a log's scans at their true poses), write
    ``map.geojson``, its picture, the trajectory, ``report.json`` (and a ROS map for real
    scans), print the summary."""
    filt, cfg, k = src.filt, src.resolved.config, done.steps
    thr = cfg.merge_threshold
    best = filt.best
    report: dict[str, Any] = {
        **src.source,
        "seed": args.seed,
        "particles": cfg.particles,
        "merge_threshold": thr,
        "config_overrides": src.resolved.recorded,
        "steps": k,
        "time_s": round(done.wall, 3),
        "filter_time_s": round(done.busy, 3),
        "updates_per_s": round(k / done.busy, 2) if done.busy > 0 else None,
        "particle_bytes": filt.memory_bytes(),
        "best_bytes": best.paper_storage_bytes(),
        "vertices": best.n_vertices,
        "edges": best.n_edges,
        "metrics": None,
        "interrupted": done.interrupted,
    }
    if src.truth is not None:
        # a map that stopped before the route's end (Ctrl-C, --steps, --duration) is partial
        cut_short = done.interrupted or (src.route_steps is not None and k < src.route_steps)
        report.update(_score_world(src.truth, best, thr, done, cut_short))
    png = None
    report.update(src.extra or {})
    if src.scans is not None and src.true_scans is not None and k:
        lidar, png = _score_log(src.scans[:k], src.true_scans[:k], done.trajectory, best, src.max_range)
        report.update(lidar)
    props = {**src.source, "steps": k, "seed": args.seed, "particles": cfg.particles, "merge_threshold": thr}
    title = f"{src.name}: one robot, {k} steps, {cfg.particles} particles"
    write_outputs(out, best, done.trajectory, report, truth=src.truth, properties=props, png=png,
                  title=title, free=src.free)
    if src.scans is not None and k and best.n_vertices:
        _write_rosmap(out, best, src.scans[:k], done.trajectory, src.max_range)
    _print_summary(report, out)


def _write_rosmap(out: Path, best: Any, scans: list[Any], trajectory: list[tuple[float, float, float, float]],
                  max_range: float) -> None:
    """``map.pgm`` + ``map.yaml`` for ROS map_server / Nav2 from a real log or bag: the map's
    walls occupied, and free what the scans' own beams crossed at the poses the map was made at
    (:func:`agents.files.export.scan_free`; the walls alone close no room of a real map)."""
    from agents.files.export import DEFAULT_RESOLUTION, write_rosmap

    poses = [(x, y, th) for _, x, y, th in trajectory]
    beams = [(s.ranges, s.angles) for s in scans]
    pts = np.concatenate([np.array([(x, y) for x, y, _ in poses], dtype=np.float64), best.points])
    lo, hi = pts.min(axis=0), pts.max(axis=0)  # the walls and the path
    try:
        write_rosmap(best, out / "map", DEFAULT_RESOLUTION, scans=(poses, beams, max_range),
                     bounds=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))
    except ValueError as exc:  # a raster over the size limit: the other outputs stand
        print(f"wiremap map: no map.pgm: {exc}", file=sys.stderr, flush=True)


def _score_world(truth: Any, best: Any, thr: float, done: _Drive, cut_short: bool) -> dict[str, Any]:
    """The map against a simulated world's truth, and the pose errors along the way; a map
    ``cut_short`` before its route's end has no cell error (unexplored area would count)."""
    from mapping.metrics import evaluate

    metrics = evaluate(truth, best, thr) if best.n_edges else None
    scored = None if metrics is None else {k2: _num(v) for k2, v in metrics.items()}
    if cut_short and scored is not None:  # an unfinished map is partial
        from agents.commands.run import MAP_CUT_SHORT, partial_note

        scored["cell_error"] = None
        scored["cell_error_note"] = partial_note(MAP_CUT_SHORT)
    err = done.pose_err
    return {
        "metrics": scored,
        "pose_error_mean_m": round(float(np.mean(err)), 4) if err else None,
        "pose_error_max_m": round(float(np.max(err)), 4) if err else None,
    }


def _print_summary(report: dict[str, Any], out: Path) -> None:
    """Aligned closing lines (the same figures as ``report.json``)."""
    m = report.get("metrics")
    ups = report.get("updates_per_s")
    lines = [
        f"wiremap map: {report['steps']} steps in {report['time_s']:.1f} s"
        + (f" ({ups:.1f} scans/s)" if ups else "") + (", interrupted" if report.get("interrupted") else ""),
        f"  map         {report['vertices']} corners, {report['edges']} walls",
    ]
    if report.get("skipped_lines"):
        lines.append(f"  log         skipped {report['skipped_lines']} unreadable lines")
    if report.get("laser_yaw_deg"):
        lines.append(f"  laser yaw   {report['laser_yaw_deg']:+.2f} degrees taken off every bearing "
                     f"(+-{report['laser_yaw_se_deg']:.2f})")
    if report.get("slam_odo_rot_per_m_deg") is not None:
        noise = report["odometry_heading_noise_deg_per_m"]
        measured = "not measured" if noise is None else f"{noise:.2f} deg/m"
        lines.append(f"  odometry    heading error {measured} ({report['odometry_noise_pairs']} scan pairs)")
        lines.append(f"              SLAM prior {report['slam_odo_rot_per_m_deg']:.2f} deg/m"
                     + (" (widened)" if report.get("slam_odo_prior_widened") else " (as configured)"))
    if report.get("input") == "rosbag":
        line = (f"  bag         {report['scans']} scans from {report['scan_topic']}, "
                f"odometry {report['odometry']}")
        if report.get("skipped_messages"):
            line += f", skipped {report['skipped_messages']} unreadable messages"
        if report.get("unposed_scans"):
            line += f", {report['unposed_scans']} scans without odometry at their time"
        lines.append(line)
    if m:
        lines.append(
            f"  vs truth    cell error {_pct(m['cell_error'])}, wall precision {m['wall_precision']:.3f}, "
            f"recall {m['wall_recall']:.3f}"
        )
    if report.get("ate_rmse_m") is not None:
        lines.append(f"  vs truth    ATE {report['ate_rmse_m']:.3f} m "
                     f"(odometry {report['odometry_ate_rmse_m']:.3f} m)")
        if report.get("map_precision") is not None:
            lines.append(f"              map precision {report['map_precision']:.3f}, "
                         f"coverage {report['map_coverage']:.3f}")
            if report.get("map_precision_aligned") is not None:
                lines.append(f"              precision {report['map_precision_aligned']:.3f} after one rigid "
                             f"move of {report['alignment_m']:.2f} m, {report['alignment_deg']:+.2f} deg")
    if report.get("pose_error_mean_m") is not None:
        lines.append(f"  pose error  mean {report['pose_error_mean_m']:.3f} m, "
                     f"max {report['pose_error_max_m']:.3f} m")
    lines.append(f"  wrote       in {out}: map.geojson map.png trajectory.tsv report.json")
    if report.get("input") in ("carmen", "rosbag") and (out / "map.pgm").is_file():
        lines.append("              map.pgm map.yaml (a ROS map for Nav2)")
    print("\n".join(lines), flush=True)


def _pct(v: Any) -> str:
    return "n/a (map cut short)" if v is None else f"{float(v):.2%}"


def _score_log(
    scans: list[Any], truth: list[Any], trajectory: list[tuple[float, float, float, float]], best: Any,
    max_range: float,
) -> tuple[dict[str, Any], bytes]:
    """Scores of a CARMEN run against its true poses (:mod:`mapping.lidar_metrics`) and the
    picture of the map over the real endpoints at those poses."""
    from agents.bench.lidar_png import lidar_png
    from mapping.lidar_metrics import ate, scan_endpoints, score_run

    true_xyt = np.array([[p.x, p.y, p.theta] for p in truth], dtype=np.float64)
    est = np.array([(x, y, th) for _, x, y, th in trajectory], dtype=np.float64)
    odom = np.array([[s.odom.x, s.odom.y, s.odom.theta] for s in scans], dtype=np.float64)
    ends = scan_endpoints(true_xyt, [s.ranges for s in scans], [s.angles for s in scans], max_range=max_range)
    scores = score_run(est, true_xyt, best, ends)
    scores["odometry_ate_rmse_m"] = ate(odom, true_xyt)[0]
    png = lidar_png(best, ends, true_xyt[:, :2], est[:, :2], title=f"ate {scores['ate_rmse_m']:.2f} m")
    return {k: _num(v) for k, v in scores.items()}, png


def _num(v: Any) -> Any:
    f = float(v)
    return None if math.isnan(f) else round(f, 6)
