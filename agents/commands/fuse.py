"""``wiremap fuse [--store DIR] [--rrd FILE] [--serve-viewer PORT] [--connect ...]``: the fusion
service. Keeps each robot's latest map, fuses them in the fleet frame, publishes the fused map
on ``wiremap/<fleet>/fused/map`` (and answers queries for it), stores its state, records to
Rerun. Stops cleanly on SIGINT/SIGTERM. See :mod:`agents.fleet.fusion`."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from agents.errors import UserError
from agents.files.io import output_file
from agents.fleet.bus import (
    StopFlag,
    add_bus_arguments,
    check_name,
    config_from_args,
    fleet_keys,
    open_session,
    watch_parent,
)
from agents.fleet.fusion import InputLimits
from agents.fleet.fusion.frames import FramesConfig

HELP = "the fusion service"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--store", metavar="DIR",
                        help="state directory: resume from it and keep it up to date")
    parser.add_argument(
        "--reset",
        action="store_true",
        help="when the --store cannot be recovered, move its files aside and start empty "
        "(without it: one line and exit 2)",
    )
    parser.add_argument("--rrd", metavar="FILE", help="write a Rerun recording to FILE")
    parser.add_argument(
        "--serve-viewer", metavar="PORT", type=int, help="also serve the recording to a live viewer on PORT"
    )
    parser.add_argument("--world", metavar="NAME|FILE", help="draw this world's true walls in the recording")
    parser.add_argument("--recording-id", help="Rerun recording id (default: a new one)")
    parser.add_argument(
        "--threshold", type=float,
        help="merge threshold in metres (default 0.2, or the coarsest robot-map resolution if larger)"
    )
    parser.add_argument("--no-refine", action="store_true", help="trust the start poses, no ICP refinement")
    parser.add_argument(
        "--anchor", metavar="ID",
        help="robots of unknown start pose: the fleet frame is this robot's (default: the first registered)",
    )
    parser.add_argument(
        "--heartbeat", type=float, default=3.0, metavar="S",
        help="re-publish the fused map every S s (default 3)"
    )
    parser.add_argument(
        "--min-interval", type=float, default=0.0, metavar="S",
        help="fuse at most every S seconds, batching what arrives meanwhile (default 0; the root too)"
    )
    parser.add_argument(
        "--save-interval",
        type=float,
        default=1.0,
        metavar="S",
        help="write the store at most every S seconds; 0: on every change (default 1)",
    )
    d = InputLimits()
    parser.add_argument(
        "--max-map-bytes",
        type=int,
        default=d.max_bytes,
        metavar="N",
        help=f"drop robot maps larger than N bytes (default {d.max_bytes})",
    )
    parser.add_argument(
        "--rate-limit",
        type=float,
        default=d.rate_hz,
        metavar="HZ",
        help=f"maps per second accepted per robot key, bursts of {d.burst} (default {d.rate_hz:g})",
    )
    parser.add_argument(
        "--max-extent",
        type=float,
        default=d.max_extent_m,
        metavar="M",
        help=f"drop maps with a vertex further than M metres from the fleet origin "
        f"(default {d.max_extent_m:g})",
    )
    add_tree_arguments(parser)
    add_bus_arguments(parser)


def add_tree_arguments(parser: argparse.ArgumentParser) -> None:
    """The fusion tree's flags (:mod:`agents.fleet.fusion.regional`, :mod:`agents.fleet.fusion.root`)."""
    g = parser.add_argument_group("fusion tree")
    g.add_argument("--group", metavar="NAME",
                   help="be a regional fuser: publish the partial map of --robots on groups/NAME/map")
    g.add_argument(
        "--robots", metavar="PATTERN",
        help="the regional fuser's robots: glob patterns over ids, comma-separated (r0[1-8],r1*), "
        "or hash:I/K",
    )
    g.add_argument(
        "--of-groups", metavar="NAME,NAME|*",
        help="be the root fuser: merge these groups' partial maps (* = every group) into fused/map",
    )
    g.add_argument("--no-standby", action="store_true",
                   help="a regional fuser does not take over a dead one's robots")


def run_tree(args: argparse.Namespace, say: Any) -> int | None:
    """``--of-groups``: run the root fuser and return its exit status; ``--group``: check the
    regional fuser's flags and return None (:func:`run` runs it); None for neither."""
    if args.group is None and args.of_groups is None and args.robots is None:
        return None
    from agents.fleet.bus import valid_name
    from agents.fleet.fusion.tree import RobotSelector

    if args.of_groups is not None and (args.group is not None or args.robots is not None):
        raise UserError("--of-groups (the root) does not take --group or --robots")
    if args.of_groups is not None:
        names = (
            None
            if args.of_groups.strip() == "*"
            else [g.strip() for g in args.of_groups.split(",") if g.strip()]
        )
        for n in names or []:
            if not valid_name(n) or n == "root":
                raise UserError(f"--of-groups: {n!r} is not a group name")
        if not (math.isfinite(args.min_interval) and args.min_interval >= 0):
            raise UserError(f"--min-interval must be a number >= 0, got {args.min_interval}")
        if args.store:
            from agents.files.io import check_output_dir
            from agents.fleet.fusion.root import read_root_store

            check_output_dir("--store", args.store)
            if not args.reset:
                read_root_store(args.store)  # unreadable: one line, exit 2, before any router
        if args.rrd:
            output_file("--rrd", args.rrd)
        if args.serve_viewer is not None and not args.rrd:
            raise UserError("--serve-viewer needs --rrd FILE (the recording always goes to a file)")
        if args.world:
            from agents.sim.world import load_world

            load_world(args.world)
        return _serve(args, say, lambda session, keys, stop: _root(session, keys, stop, names, args, say))
    if args.group is None or args.robots is None:
        raise UserError("a regional fuser needs both --group NAME and --robots PATTERN")
    if not valid_name(args.group) or args.group == "root":
        raise UserError(f"--group {args.group!r}: letters, digits, '_', '.', '-' (and not 'root')")
    RobotSelector.parse(args.robots)  # a bad pattern is one line at once
    return None


def _root(session: Any, keys: Any, stop: Any, names: Any, args: argparse.Namespace, say: Any) -> None:
    from agents.fleet.fusion.root import serve_root

    recording = {"rrd": args.rrd, "serve_viewer": args.serve_viewer, "recording_id": args.recording_id,
                 "world": args.world}
    svc = serve_root(session, keys, names, stop, args.threshold, max(0.1, args.heartbeat), args.store, say,
                     args.reset, recording, args.min_interval)
    st = svc.state
    say(f"stopped at v{st.version}: {st.fused.n_vertices} vertices, {st.fused.n_edges} edges from "
        f"{len(st.fused_robots)} robots in {len(st.partials)} groups (exact {st.exact})")


def _serve(args: argparse.Namespace, say: Any, body: Any) -> int:
    keys = fleet_keys(args)
    cfg = config_from_args(args, "client")
    if args.store:
        Path(args.store).mkdir(parents=True, exist_ok=True)
    with StopFlag() as stop:
        watch_parent(args.parent_pid, stop)
        session = open_session(cfg, stop, on_wait=lambda t: say(f"waiting for a router ({t})"))
        if session is None:
            return 0
        try:
            body(session, keys, stop.event)
        finally:
            session.close()
    sys.stdout.flush()
    return 0


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from agents.fleet.fusion import FusionConfig, ServeOptions, serve

    def say(text: str) -> None:
        print(f"wiremap fuse: {text}", flush=True)

    tree = run_tree(args, say)
    if tree is not None:
        return tree
    if args.serve_viewer is not None and not args.rrd:
        raise UserError("--serve-viewer needs --rrd FILE (the recording always goes to a file)")
    if args.threshold is not None and not (math.isfinite(args.threshold) and args.threshold > 0):
        raise UserError(f"--threshold must be a positive number of metres, got {args.threshold}")
    for name, v in (("--rate-limit", args.rate_limit), ("--max-extent", args.max_extent),
                    ("--heartbeat", args.heartbeat)):
        if not (math.isfinite(v) and v > 0):
            raise UserError(f"{name} must be a positive number, got {v}")
    for name, v in (("--save-interval", args.save_interval), ("--min-interval", args.min_interval)):
        if not (math.isfinite(v) and v >= 0):
            raise UserError(f"{name} must be a number >= 0, got {v}")
    if args.max_map_bytes < 64:
        raise UserError(f"--max-map-bytes must be at least 64, got {args.max_map_bytes}")
    # files and the world are checked before waiting for a router: a typo is one line at once
    if args.store:
        from agents.files.io import check_output_dir

        check_output_dir("--store", args.store)
        try:
            Path(args.store).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"--store {args.store}: cannot create it: {exc.strerror or exc}") from None
        if not args.reset:
            from agents.fleet.fusion import read_store

            read_store(args.store)  # StoreDamaged (one line, exit 2) before waiting for a router
    if args.rrd:
        output_file("--rrd", args.rrd)
    if args.world:
        from agents.sim.world import load_world

        load_world(args.world)
    limits = dataclasses.replace(
        InputLimits(), max_bytes=args.max_map_bytes, rate_hz=args.rate_limit, max_extent_m=args.max_extent
    )
    opts = ServeOptions(
        store=args.store,
        rrd=args.rrd,
        serve_viewer=args.serve_viewer,
        world=args.world,
        recording_id=args.recording_id,
        heartbeat_s=max(0.1, args.heartbeat),
        min_interval_s=args.min_interval,
        save_interval_s=args.save_interval,
        reset=args.reset,
        # a regional fuser publishes a node of the fold tree: frontiers are closed at the root
        config=FusionConfig(threshold=args.threshold, refine=not args.no_refine,
                            close_frontiers=args.group is None),
        limits=limits,
        frames=FramesConfig(anchor=check_name(args.anchor) if args.anchor else None),
    )
    keys = fleet_keys(args)
    cfg = config_from_args(args, "client")
    if args.group is not None:
        from agents.fleet.fusion.regional import serve_regional
        from agents.fleet.fusion.tree import RobotSelector

        sel = RobotSelector.parse(args.robots)
        group_name = args.group

        def say(text: str) -> None:
            print(f"wiremap fuse [{group_name}]: {text}", flush=True)
    with StopFlag() as stop:
        watch_parent(args.parent_pid, stop)
        session = open_session(cfg, stop, on_wait=lambda t: say(f"waiting for a router ({t})"))
        if session is None:
            return 0
        try:
            if args.group is not None:
                state = serve_regional(session, keys, opts, args.group, sel, stop.event, say,
                                       standby=not args.no_standby).state
            else:
                state = serve(session, keys, opts, stop.event, say)
        finally:
            session.close()
    s = state.stats.as_dict()
    lat = s["latency_ms"]
    say(
        f"stopped at v{state.version}: {state.fused.n_vertices} vertices, {state.fused.n_edges} edges from "
        f"{len(state.robots)} robots; {s['accepted']} maps accepted, {s['superseded']} superseded, "
        f"{s['malformed']} malformed, "
        f"{s['rejected']} rejected, {s['absurd']} absurd, {s['oversized']} oversized, "
        f"{s['rate_limited']} rate-limited, {s['overflow']} overflowed; "
        f"latency p50 {_ms(lat['p50'])} ms p99 {_ms(lat['p99'])} ms"
    )
    sys.stdout.flush()
    if state.exit_error:
        print(f"wiremap fuse: {state.exit_error}", file=sys.stderr, flush=True)
        return 1
    return 0


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"
