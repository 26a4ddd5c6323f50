"""``wiremap robot --id ID --world NAME|FILE --start X,Y,THETA [--route ...] [--rate HZ] [--seed S]
[--sensor corners|lidar|lidar-real [--scene-seed S]] [--params FILE] [--set KEY=VALUE ...]
[--connect ...]``: one simulated robot with its own particle filter, publishing its map, pose and
liveliness on the bus until SIGINT/SIGTERM. See :mod:`agents.fleet.robot`; ``--params``/``--set``:
:mod:`agents.params` (``--particles`` and ``--threshold`` are shorthands for ``--set particles=``
and ``--set merge_threshold=``); ``--sensor``: :data:`agents.mapping_run.SENSORS`."""

from __future__ import annotations

import argparse
import itertools
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.argtypes import add_bag_topics, non_negative_float, non_negative_int, positive_float, scan_range
from agents.errors import UserError
from agents.fleet.bus import (
    StopFlag,
    add_bus_arguments,
    check_name,
    config_from_args,
    fleet_keys,
    open_session,
    watch_parent,
)
from agents.fleet.robot import DEFAULT_RESOLUTION, DEFAULT_THRESHOLD
from agents.mapping_run import LIDAR_PROFILES, SENSORS
from agents.params import ConfigArgs, Resolved, add_config_arguments, resolve
from mapping.se2 import Pose

if TYPE_CHECKING:
    from agents.fleet.robot import RobotOptions

HELP = "one robot agent process"
DEFAULT_RATE = 5.0  # a simulated or replayed robot's scans per second
MAX_CALIBRATION_SCANS = 10_000  # a live robot's scans held for its calibrations, at most


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", required=True, help="robot id (letters, digits, '_', '.', '-')")
    parser.add_argument("--world", metavar="NAME|FILE",
                        help="built-in world name or world file (or give --carmen)")
    parser.add_argument(
        "--unknown-start", action="store_true",
        help="publish the map in the robot's own frame with its origin marked unknown (fusion registers it)",
    )
    parser.add_argument("--carmen", metavar="LOG",
                        help="replay this CARMEN log instead of simulating a world")
    parser.add_argument("--rosbag", metavar="FILE",
                        help="replay the LaserScan of this ROS bag instead of simulating a world "
                        "(ROS 1 .bag, ROS 2 bag folder or its .db3/.mcap file; as wiremap map --rosbag)")
    add_bag_topics(parser, "with --rosbag: ")
    parser.add_argument("--truth-topic", metavar="TOPIC",
                        help="with --rosbag: read the bag as wiremap run --truth-topic does (scans "
                        "without a true pose left out), so that --scans indexes the same scans")
    parser.add_argument("--scans", type=scan_range, metavar="I0:I1",
                        help="with --carmen or --rosbag: replay the log's scans I0 to I1-1")
    parser.add_argument(
        "--scan-key", metavar="KEY",
        help="map the robot's own lidar, live: ROS 2 sensor_msgs/LaserScan (CDR) on this Zenoh key "
        "expression (zenoh-bridge-ros2dds: the topic's name, e.g. scan; rmw_zenoh: */scan/**); "
        "needs --odom-key",
    )
    parser.add_argument(
        "--odom-key", metavar="KEY",
        help="with --scan-key: nav_msgs/Odometry (CDR) on this Zenoh key expression (e.g. odom)",
    )
    parser.add_argument(
        "--laser-mount", metavar="X,Y[,THETA]",
        help="with --scan-key: the laser's pose on the robot's base (metres, radians; default 0,0,0)",
    )
    parser.add_argument(
        "--tf-key", metavar="KEY", default=None,
        help="with --scan-key: find the laser's mount from the tf2_msgs/TFMessage on KEY (the robot's "
        "/tf_static: 'tf_static' through zenoh-bridge-ros2dds) instead of --laser-mount",
    )
    parser.add_argument(
        "--base-frame", metavar="FRAME", default=None,
        help="with --tf-key: the robot's base frame, the mount's parent (default the odometry's "
        "child_frame_id, else base_link)",
    )
    parser.add_argument(
        "--min-travel", type=non_negative_float, default=None, metavar="M",
        help="with --scan-key: map a scan once the wheels have moved M metres since the last one "
        "mapped (default 0.5; 0 with --min-turn 0: every scan)",
    )
    parser.add_argument(
        "--min-turn", type=non_negative_float, default=None, metavar="DEG",
        help="with --scan-key: ... or turned DEG degrees (default 10)",
    )
    parser.add_argument(
        "--reversed-sweep", action="store_true",
        help="with --scan-key: the lidar's beams come in the order opposite to the one its "
        "time_increment says (the TurtleBot3 LDS-01 driver's default, chronological_order false); "
        "de-skew them the other way round until the order is judged on the scans that came while "
        "calibrating (enough of them turning: the order they fit best)",
    )
    parser.add_argument(
        "--calibration-scans", type=int, default=None, metavar="N",
        help="with --scan-key: scans held at the start to calibrate the laser's yaw and the wheels' "
        "noise before the first is mapped (default 30)",
    )
    parser.add_argument(
        "--lidar-profile", choices=tuple(LIDAR_PROFILES), default=None,
        help="with --carmen: lidar-slam, lidar SLAM over the stretch under the filter (default), or "
        "lidar, the filter's corner ICP alone (as wiremap map --lidar-profile); with --scan-key: "
        "lidar-slam-online (the default and the only one that maps scans as they come)",
    )
    parser.add_argument(
        "--start", metavar="X,Y[,THETA]",
        help="start position in the fleet frame, metres (default: the route's start); the simulated robot "
        "starts facing along its route, so a THETA (radians) that differs is reported and replaced",
    )
    parser.add_argument(
        "--route",
        metavar="X,Y;X,Y;...|FILE",
        help="waypoints, or a JSON file of [[x, y], ...] (default: a coverage route from --start)",
    )
    parser.add_argument("--rate", type=float, default=None, metavar="HZ",
                        help="scans per second (default 5; not with --scan-key: a live lidar's scans "
                        "are mapped as they come)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--sensor", choices=SENSORS, default="corners",
        help="simulated sensor: corner sensor (default), clean lidar, or realistic lidar (lidar-real)",
    )
    parser.add_argument(
        "--scene-seed", type=non_negative_int, default=None, metavar="S",
        help="with --sensor lidar-real: seed of the scene (glass, clutter, people; default --seed); "
        "robots of one fleet share it",
    )
    parser.add_argument("--particles", type=int, default=None, help="particles of the filter (default 5)")
    parser.add_argument(
        "--resolution", type=float, default=DEFAULT_RESOLUTION, metavar="M",
        help=f"quantisation step of the published map's coordinates (default {DEFAULT_RESOLUTION:g})",
    )
    parser.add_argument(
        "--threshold", type=float, default=None, metavar="M",
        help=f"merge threshold of the particle filter (default {DEFAULT_THRESHOLD:g}; "
             "the paper: 0.4 in a large world)",
    )
    parser.add_argument(
        "--heartbeat", type=float, default=2.0, metavar="S",
        help="re-send the map at least every S s (default 2)"
    )
    parser.add_argument("--viz-rate", type=non_negative_float, default=2.0, metavar="HZ",
                        help="scan+particles for the recorder, Hz (0: off)")
    parser.add_argument(
        "--duration", type=positive_float, metavar="S",
        help="stop mapping after S simulated seconds (simulated time runs 2.5x the wall clock at --rate 5: "
        "each scan is 0.5 s of driving); with --scan-key: S seconds of the lidar's stamps after the "
        "first scan, checked at each scan mapped",
    )
    parser.add_argument(
        "--router-timeout", type=float, metavar="S",
        help="give up (exit 2) when no router answers within S seconds (default: wait; "
        "says what it tries every 10 s)",
    )
    parser.add_argument("--status-file", metavar="FILE",
                        help="write the final status as JSON to FILE on exit")
    add_config_arguments(parser, "--particles, --threshold")
    add_bus_arguments(parser)


def options_from_args(args: argparse.Namespace) -> RobotOptions:
    from agents.fleet.robot import RobotOptions, parse_route, start_pose_of

    rid = check_name(args.id)
    live = bool(args.scan_key or args.odom_key)
    if live and args.rate is not None:
        raise UserError("--rate is for a simulated or replayed robot; a live lidar maps scans as they come")
    if args.rate is None:
        args.rate = DEFAULT_RATE
    if (args.scan_topic or args.odom_topic or args.truth_topic) and not args.rosbag:
        raise UserError("--scan-topic, --odom-topic and --truth-topic are for --rosbag")
    if live:
        if args.carmen or args.world or args.rosbag:
            raise UserError("--scan-key maps a live lidar: give it without --carmen, --rosbag or --world")
        if args.sensor != "corners" or args.scene_seed is not None or args.route:
            raise UserError("--sensor, --scene-seed and --route are for a simulated world; "
                            "--scan-key maps the robot's own lidar")
        return _live_options(args, rid)
    if args.laser_mount or args.calibration_scans is not None or args.min_travel is not None \
            or args.min_turn is not None or args.tf_key or args.base_frame or args.reversed_sweep:
        raise UserError("--laser-mount, --tf-key, --base-frame, --calibration-scans, --min-travel, "
                        "--min-turn and --reversed-sweep are for a live lidar (--scan-key)")
    if args.carmen and args.rosbag:
        raise UserError("give --carmen LOG or --rosbag FILE, not both")
    if args.carmen or args.rosbag:
        if args.sensor != "corners" or args.scene_seed is not None:
            raise UserError("--sensor and --scene-seed are for a simulated world; "
                            f"{'--carmen' if args.carmen else '--rosbag'} replays the log's lidar")
        return _carmen_options(args, rid)
    if not args.world:
        raise UserError("give --world NAME|FILE (or --carmen LOG)")
    from agents.sim.world import load_world

    load_world(args.world)  # an unknown world or a bad file is its own one-line error, first
    route = None
    if args.route:
        try:
            route = parse_route(args.route)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    heading_given = True
    if args.start:
        text = args.start
        if text.count(",") == 1:  # X,Y: the heading comes from the route
            text, heading_given = text + ",0", False
        try:
            start = Pose.parse(text)
        except ValueError as exc:
            raise UserError(f"--start {args.start}: {exc}") from None
    elif route is not None:
        start = start_pose_of(route)
    else:
        raise UserError("give --start X,Y,THETA or --route")
    for name, v, lo in (
        ("--rate", args.rate, 0.0), ("--resolution", args.resolution, 0.0),
        ("--threshold", args.threshold, 0.0), ("--heartbeat", args.heartbeat, 0.0),
    ):
        if v is not None and not (math.isfinite(v) and v > lo):
            raise UserError(f"{name} must be a positive number, got {v}")
    if args.particles is not None and args.particles < 1:
        raise UserError(f"--particles must be >= 1, got {args.particles}")
    resolved = _filter_config(args)
    if route is not None:
        gap = float(np.hypot(*(route[0] - np.array([start.x, start.y]))))
        if gap <= 0.05:  # the same point (rounding): start exactly at --start
            route = route.copy()
            route[0] = (start.x, start.y)
        else:  # drive from --start to the route first
            route = np.vstack([[start.x, start.y], route])
    return RobotOptions(
        robot=rid,
        world=args.world,
        start=start,
        route=route,
        rate=args.rate,
        seed=args.seed,
        particles=resolved.config.particles,
        resolution=args.resolution,
        threshold=resolved.config.merge_threshold,
        heartbeat_s=args.heartbeat,
        viz_hz=max(0.0, args.viz_rate),
        duration=args.duration,
        filter_overrides=resolved.overrides,
        unknown_start=bool(args.unknown_start),
        heading_given=heading_given,
        extra=_sensor_extra(args),
    )


def _sensor_extra(args: argparse.Namespace) -> dict[str, Any]:
    """``RobotOptions.extra`` for ``--sensor`` and ``--scene-seed`` (read by
    :func:`agents.mapping_run.robot_steps`); empty for the default corner sensor."""
    extra: dict[str, Any] = {}
    if args.sensor != "corners":
        extra["sensor"] = args.sensor
    if args.scene_seed is not None:
        extra["scene_seed"] = int(args.scene_seed)
    return extra


def _filter_config(args: argparse.Namespace) -> Resolved:
    """The filter's settings (checked now, so that a bad one is an error before the bus)."""
    from agents.mapping_run import filter_config_for

    flags = {"particles": ("--particles", args.particles), "merge_threshold": ("--threshold", args.threshold)}
    return resolve(
        ConfigArgs.from_args(args),
        lambda ov: filter_config_for(5, DEFAULT_THRESHOLD, 8.0, overrides=ov),
        {k: v for k, v in flags.items() if v[1] is not None},
    )


def _carmen_options(args: argparse.Namespace, rid: str) -> RobotOptions:
    """A robot replaying (part of) a CARMEN log or a ROS bag, always in its own frame (unknown
    start)."""
    from agents.fleet.robot import RobotOptions

    extra: dict[str, Any] = {}
    if args.rosbag:
        from pathlib import Path

        if not Path(args.rosbag).exists():
            raise UserError(f"--rosbag {args.rosbag}: no such file or folder")
        extra["rosbag"] = {"scan_topic": args.scan_topic, "odom_topic": args.odom_topic,
                           "truth_topic": args.truth_topic}

    scans = args.scans
    resolved = _filter_config(args)
    return RobotOptions(
        robot=rid, world="", start=Pose.identity(), rate=args.rate, seed=args.seed,
        particles=resolved.config.particles, resolution=args.resolution,
        threshold=resolved.config.merge_threshold, heartbeat_s=args.heartbeat,
        viz_hz=max(0.0, args.viz_rate), duration=args.duration, unknown_start=True,
        carmen=args.carmen or args.rosbag, scans=scans, filter_overrides=resolved.overrides,
        lidar_profile=args.lidar_profile or "lidar-slam", extra=extra,
    )


def _live_options(args: argparse.Namespace, rid: str) -> RobotOptions:
    """A robot mapping its own lidar, live (:mod:`agents.fleet.live_lidar`): in the fleet frame
    from ``--start`` when given, else in its own frame (unknown start, registered by fusion)."""
    from agents.fleet.live_lidar import check_keys, parse_mount
    from agents.fleet.robot import RobotOptions

    if not (args.scan_key and args.odom_key):
        raise UserError("a live lidar needs both --scan-key and --odom-key")
    if args.scans:
        raise UserError("--scans is for --carmen and --rosbag; a live lidar maps every scan that comes")
    check_keys(args.scan_key, args.odom_key)
    profile = args.lidar_profile or "lidar-slam-online"
    if profile != "lidar-slam-online":
        raise UserError(f"--lidar-profile {profile} needs the whole log first; a live lidar maps with "
                        "lidar-slam-online (its SLAM runs scan by scan)")
    extra: dict[str, Any] = {}
    if args.calibration_scans is not None:
        if not 1 <= args.calibration_scans <= MAX_CALIBRATION_SCANS:
            raise UserError(f"--calibration-scans must be within 1..{MAX_CALIBRATION_SCANS}, "
                            f"got {args.calibration_scans}")
        extra["calibration_scans"] = int(args.calibration_scans)
    if args.min_travel is not None:
        extra["min_travel"] = float(args.min_travel)
    if args.min_turn is not None:
        extra["min_turn"] = math.radians(float(args.min_turn))
    if args.reversed_sweep:
        extra["sweep_reversed"] = True
    mount = Pose.identity()
    if args.laser_mount:
        if args.tf_key:
            raise UserError("give the laser's mount as --laser-mount or find it with --tf-key, not both")
        try:
            mount = parse_mount(args.laser_mount)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    if args.base_frame is not None and not args.tf_key:
        raise UserError("--base-frame is the mount's parent frame for --tf-key")
    if args.tf_key:
        check_keys(args.scan_key, args.odom_key, args.tf_key)
        extra["tf_key"] = args.tf_key
        if args.base_frame is not None:
            extra["base_frame"] = args.base_frame.lstrip("/")
            if not extra["base_frame"]:
                raise UserError("--base-frame must name a frame")
    start, unknown = Pose.identity(), True
    if args.start:
        text = args.start if args.start.count(",") == 2 else args.start + ",0"
        try:
            start = Pose.parse(text)
        except ValueError as exc:
            raise UserError(f"--start {args.start}: {exc}") from None
        unknown = bool(args.unknown_start)
    for name, v in (("--resolution", args.resolution), ("--threshold", args.threshold),
                    ("--heartbeat", args.heartbeat)):
        if v is not None and not (math.isfinite(v) and v > 0.0):
            raise UserError(f"{name} must be a positive number, got {v}")
    resolved = _filter_config(args)
    return RobotOptions(
        robot=rid, world="", start=start, rate=0.0, seed=args.seed,
        particles=resolved.config.particles, resolution=args.resolution,
        threshold=resolved.config.merge_threshold, heartbeat_s=args.heartbeat,
        viz_hz=max(0.0, args.viz_rate), duration=args.duration, unknown_start=unknown,
        filter_overrides=resolved.overrides, lidar_profile=profile,
        live=(args.scan_key, args.odom_key), mount=mount, extra=extra,
    )


def _calibration_scans(opts: RobotOptions) -> int:
    from agents.fleet.live_lidar import live_profile

    return int(live_profile(opts)[2].calibration_scans)


TF_HISTORY = 16  # latched transform messages asked of each publisher's cache


def _live_steps(session: Any, opts: RobotOptions, stop: Any, subs: list[Any]) -> tuple[Any, Any]:
    """Subscribe to the live scans and odometry (``subs`` gets the subscribers); the robot's
    steps over them (:func:`agents.fleet.live_lidar.live_steps`) and the source's counters."""
    from agents.fleet.live_lidar import LiveLidar, live_steps

    assert opts.live is not None
    tf_key = opts.extra.get("tf_key")
    source = LiveLidar(mount=opts.mount, use_transforms=bool(tf_key), base_frame=opts.extra.get("base_frame"))
    subs.append(session.declare_subscriber(opts.live[0], lambda s: source.on_scan(s.payload)))
    subs.append(session.declare_subscriber(opts.live[1], lambda s: source.on_odometry(s.payload)))
    if tf_key:
        # /tf_static is latched (transient local): sent once, before this robot may have come. An
        # advanced subscriber with history gets it from a publisher's cache (zenoh-bridge-ros2dds
        # keeps one with Advanced Pub/Sub; `wiremap play --tf-key` too), and later ones as they come.
        from zenoh.ext import HistoryConfig, declare_advanced_subscriber

        subs.append(declare_advanced_subscriber(
            session, tf_key, lambda s: source.on_transforms(s.payload),
            history=HistoryConfig(detect_late_publishers=True, max_samples=TF_HISTORY)))
    return live_steps(opts, source, stop), source.snapshot


def run(args: argparse.Namespace) -> int:
    from agents.fleet.robot import RobotAgent, default_steps

    opts = options_from_args(args)
    keys = fleet_keys(args)
    cfg = config_from_args(args, "client")
    rid = opts.robot
    if args.status_file:
        from agents.files.io import output_file

        output_file("--status-file", args.status_file)

    def say(text: str) -> None:
        print(f"wiremap robot {rid}: {text}", flush=True)

    steps: Any = None
    if opts.live is None:
        # load the world and take the first scan before going on the bus, so that a bad world,
        # start or route is a one-line error, not a traceback in the middle of the run
        steps = default_steps(opts)
        try:
            first = next(steps)
        except StopIteration:
            first = None
        except ValueError as exc:
            raise UserError(f"cannot simulate {rid} in {args.world}: {exc}") from None
        steps = itertools.chain([first], steps) if first is not None else iter(())
    with StopFlag() as stop:
        watch_parent(args.parent_pid, stop)
        if args.router_timeout is not None and not (
            math.isfinite(args.router_timeout) and args.router_timeout > 0
        ):
            raise UserError(
                f"--router-timeout must be a positive number of seconds, got {args.router_timeout}"
            )
        session = open_session(
            cfg, stop, timeout=args.router_timeout, on_wait=lambda t: say(f"waiting for a router ({t})")
        )
        if session is None:
            return 0
        live_subs: list[Any] = []
        try:
            counts = None
            if opts.live is not None:
                steps, counts = _live_steps(session, opts, stop, live_subs)
            agent = RobotAgent(session, keys, opts, steps, say, live_counts=counts)
            try:
                agent.start()
                if opts.live is not None:
                    sensor = (f" (live lidar: scans on {opts.live[0]}, odometry on {opts.live[1]}; "
                              f"{'unknown start' if opts.unknown_start else 'start given'}; the first "
                              f"{_calibration_scans(opts)} scans calibrate, then each is mapped as it comes)")
                elif opts.carmen:
                    sensor = f" (lidar profile {opts.lidar_profile})"
                else:
                    sensor = f" (sensor {opts.extra.get('sensor', 'corners')})"
                say(f"on the bus as {keys.robot_map(rid)}{sensor}")
                st = agent.run(stop)
            finally:
                agent.close()
        finally:
            for sub in live_subs:
                try:
                    sub.undeclare()
                except Exception:  # the session is already closed
                    pass
            session.close()
    say(f"stopped after {st.step} steps (t={st.t:.1f} s): {st.maps_sent} maps, {st.bytes_sent} bytes")
    if st.live is not None:
        say("live lidar: " + ", ".join(f"{k} {v}" for k, v in st.live.items()
                                       if k != "last_issue" and v != "")  # (no mount, no order yet)
            + (f"; last issue: {st.live['last_issue']}" if st.live.get("last_issue") else ""))
    if args.status_file:
        from agents.files.io import write_json

        write_json(args.status_file, {"robot": rid, **st.as_dict()})
    return 0
