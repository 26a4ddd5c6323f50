"""``wiremap play (--carmen LOG | --rosbag FILE) --scan-key KEY --odom-key KEY [--speed X]
[--scans I0:I1] [--connect ...]``: publish a log's scans and odometry on Zenoh as a ROS 2 robot
would (``sensor_msgs/LaserScan`` and ``nav_msgs/Odometry``, CDR; :mod:`agents.files.ros_messages`),
at the log's own pace times ``--speed``, so that a live robot (``wiremap robot --scan-key KEY
--odom-key KEY``) can be tried, and a setup checked, without a robot. Per scan, the odometry at
the scan's stamp goes first, then the scan. Stops at the log's end (``--loop``: never; each pass
stamped after the last) or on Ctrl-C/SIGTERM; one progress line every 10 s."""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path
from typing import Any

from agents.argtypes import add_bag_topics, positive_float, scan_range
from agents.errors import UserError
from agents.fleet.bus import StopFlag, add_bus_arguments, config_from_args, open_session, watch_parent

HELP = "publish a log's scans and odometry as a ROS 2 robot would"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--carmen", metavar="LOG", help="a CARMEN log to play")
    src.add_argument("--rosbag", metavar="FILE", help="a ROS bag to play (its LaserScan and odometry)")
    add_bag_topics(parser, "with --rosbag: ")
    parser.add_argument("--scan-key", required=True, metavar="KEY",
                        help="Zenoh key the scans go on (as a live robot's --scan-key)")
    parser.add_argument("--odom-key", required=True, metavar="KEY",
                        help="Zenoh key the odometry goes on (as a live robot's --odom-key)")
    parser.add_argument("--speed", type=positive_float, default=1.0, metavar="X",
                        help="times the log's own pace (default 1)")
    parser.add_argument("--scans", type=scan_range, metavar="I0:I1",
                        help="play the log's scans I0 to I1-1 (default all)")
    parser.add_argument("--rate", type=positive_float, default=10.0, metavar="HZ",
                        help="scans per second for a log whose scan times do not increase (default 10)")
    parser.add_argument("--tf-key", metavar="KEY", default=None,
                        help="also send the laser's mount as a latched tf2_msgs/TFMessage (base_link -> "
                        "laser) on KEY, as a robot's /tf_static (a live robot's --tf-key)")
    parser.add_argument("--loop", action="store_true",
                        help="start again at the end, until stopped (each pass stamped after the last; "
                        "the odometry jumps back to the start: a kidnapped robot)")
    add_bus_arguments(parser)


def _scans(args: argparse.Namespace) -> list[Any]:
    from agents.fleet.carmen_fleet import read_log

    if args.rosbag:
        if not Path(args.rosbag).exists():
            raise UserError(f"--rosbag {args.rosbag}: no such file or folder")
        scans = read_log(args.rosbag, {"scan_topic": args.scan_topic, "odom_topic": args.odom_topic})
    else:
        if args.scan_topic or args.odom_topic:
            raise UserError("--scan-topic and --odom-topic are for --rosbag")
        if not Path(args.carmen).is_file():
            raise UserError(f"--carmen {args.carmen}: no such file")
        scans = read_log(args.carmen)
    if args.scans:
        scans = scans[args.scans[0]:args.scans[1]]
    scans = [ls for ls in scans if len(ls.ranges) >= 1]  # a scan line with no beams is no LaserScan
    if not scans:
        raise UserError(f"{args.carmen or args.rosbag}: no scans to play")
    mounts = {ls.mount.as_tuple() for ls in scans}
    if len(mounts) > 1:
        raise UserError(f"{args.carmen or args.rosbag}: the scans have {len(mounts)} different laser mounts; "
                        "a live robot takes one (--laser-mount): play a stretch with one (--scans)")
    return live_times(scans, args.rate)


def live_times(scans: list[Any], rate: float) -> list[Any]:
    """The scans with times a live robot can pair: the log's own when they increase and are
    positive; shifted to start at 1 s when the first is not (a zero stamp means "none" in ROS);
    every ``1 / rate`` s from 1 s when they do not increase (some logs stamp every scan alike)."""
    from dataclasses import replace

    ts = [float(ls.t) for ls in scans]
    if any(b <= a for a, b in itertools.pairwise(ts)):
        return [replace(ls, t=1.0 + k / rate) for k, ls in enumerate(scans)]
    if ts[0] < 1.0:
        return [replace(ls, t=t - ts[0] + 1.0) for ls, t in zip(scans, ts)]
    return scans


def run(args: argparse.Namespace) -> int:
    from agents.files.ros_messages import Ros2Messages
    from agents.fleet.live_lidar import check_keys

    check_keys(args.scan_key, args.odom_key, args.tf_key)
    scans = _scans(args)
    mount = scans[0].mount
    make = Ros2Messages()
    # every message made before going on the bus: a scan the codec cannot write is an error now
    msgs = [make.of_scan(ls) for ls in scans]
    span = float(scans[-1].t - scans[0].t)
    period = span + (span / max(1, len(scans) - 1) if len(scans) > 1 else 1.0)  # one pass, stamps on

    def say(text: str) -> None:
        print(f"wiremap play: {text}", flush=True)

    import zenoh

    sent = passes = 0
    with StopFlag() as stop:
        watch_parent(args.parent_pid, stop)
        session = open_session(config_from_args(args, "client"), stop,
                               on_wait=lambda t: say(f"waiting for a router ({t})"))
        if session is None:
            return 0
        latched = None
        try:
            if args.tf_key:  # latched, as /tf_static: a cache answers a robot that comes later
                from zenoh.ext import CacheConfig, MissDetectionConfig, declare_advanced_publisher

                latched = declare_advanced_publisher(
                    session, args.tf_key, cache=CacheConfig(max_samples=1),
                    sample_miss_detection=MissDetectionConfig(heartbeat=0.5, sporadic_heartbeat=None),
                    publisher_detection=True)
                latched.put(make.laser_mount(float(scans[0].t), mount))
                stop.wait(0.2)  # a robot listening has the mount before the first scan
            where = (f"on {args.tf_key} (base_link -> laser)" if args.tf_key else
                     f"--laser-mount {mount.x:.6g},{mount.y:.6g},{mount.theta:.6g}")
            say(f"{len(scans)} scans ({span:.0f} s of log) on {args.scan_key}, odometry on {args.odom_key}, "
                f"at {args.speed:g}x; the laser on the robot: {where}")
            t0, last_say = time.monotonic(), time.monotonic()
            while not stop.is_set():
                for k, ls in enumerate(scans):
                    offset = passes * period + (ls.t - scans[0].t)
                    due = t0 + offset / args.speed
                    while not stop.is_set() and time.monotonic() < due:
                        stop.wait(min(due - time.monotonic(), 0.5))
                    if stop.is_set():
                        break
                    odom, scan = msgs[k] if passes == 0 else make.of_scan(_shifted(ls, passes * period))
                    session.put(args.odom_key, odom, congestion_control=zenoh.CongestionControl.BLOCK)
                    session.put(args.scan_key, scan, congestion_control=zenoh.CongestionControl.BLOCK)
                    sent += 1
                    if time.monotonic() - last_say >= 10.0:
                        last_say = time.monotonic()
                        say(f"{sent} scans sent (pass {passes + 1})")
                else:
                    passes += 1
                    if args.loop:
                        continue
                break
        finally:
            if latched is not None:
                latched.undeclare()
            session.close()
    say(f"sent {sent} scans in {passes} full pass{'es' if passes != 1 else ''}"
        + (" (stopped)" if stop.is_set() else ""))
    return 0


def _shifted(ls: Any, dt: float) -> Any:
    from dataclasses import replace

    return replace(ls, t=ls.t + dt)
