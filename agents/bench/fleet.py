"""``wiremap bench fleet --robots 1,2,4,8,16 [--duration S] [--rate HZ] [--world W] [--json]``:
latency, bandwidth and fused-map quality by fleet size.

For each fleet size N, a fresh fleet on loopback: a router process (``wiremap router``), the
fusion service (``wiremap fuse --store``) and N robot processes, plus a bus observer inside this
process (:class:`agents.bench.common.BusObserver`). Sizes up to ``--filter-upto`` (default 2) run
real robot agents (``wiremap robot``: simulation + particle filter, ``robots_mode: "filter"``);
larger sizes run replay robots (:mod:`agents.bench.replay_robot`, ``robots_mode: "replay"``)
that publish maps recorded from real filter runs along the same routes ``wiremap run`` would give
N robots (recorded once, cached under ``--cache``), because two cores cannot run 16 filters at
10 Hz; what those sizes measure is transport and fusion.

**One process for the replay robots** (``replay_processes: 1``; ``--separate-replay`` gives
each its own, the former setup): every replay robot keeps its own Zenoh session (its own link
to the router), liveliness token, keys, payloads and rate (its ticks at a random phase, as
independent robots would be), but they share one Python process, served from one thread. On a
real fleet each robot is a computer of its own and none of them competes with the fusion
service for a CPU; here they all do, whichever way they are grouped. ``robots_cpu_share`` says
what the robots' processes used: at 16 robots 0.15-0.18 of a core in one process, 0.09-0.10
as sixteen (measured on a machine loaded by other jobs, where the publish latency did not tell
the two apart).

Robots quantise their maps at ``--resolution`` (0.05 m, ``map_resolution_m``); the filters and
the fusion merge at ``--threshold`` (``merge_threshold_m``: 0.2 m, 0.4 m in worlds over 100 m).

Measured, per size, over a window of ``--duration`` seconds that starts ``--warmup`` seconds
after every robot's first map has reached the bus:

* ``latency_ms_p50`` / ``latency_ms_p99``: from a robot's publish (``stamp_ns`` of its map) to
  the fused publish that includes it, as the fusion service measures them and appends them to
  ``store/latency.log`` (:class:`agents.bench.common.LatencyHarvest`; ``wiremap run`` reports
  the service's own summary of the same samples); only fused publishes within the window
  count (not start-up, not the final maps sent after it);
* ``transport_ms_p50`` / ``transport_ms_p99``: the part of that latency before the fusion
  service: from the robot's publish to the map's arrival in its inbox (the service's
  ``fused/stats``, over the last 10,000 maps that changed, asked at the window's end);
* ``fusion_cpu_share``: the fusion process's CPU seconds over the window's wall seconds
  (``router_cpu_share`` likewise for the router, ``robots_cpu_share`` for the robots'
  processes together);
* ``bytes_per_s_per_robot``: map payload bytes that reached the bus in the window, per second
  and robot (poses separately: ``pose_bytes_per_s_per_robot``);
* ``grid_bytes_per_s_per_robot``: what the same publishes would weigh as occupancy grids: each
  map as a raw int8 grid of its bounding box (in the robot's own frame, as the robot would
  publish it) at the map's resolution, the same resolution as the map's coordinates (0.05 m;
  :func:`agents.bench.common.grid_bytes`), one grid per map publish, cells only;
  ``grid_ratio`` = those grid bytes / the map payload bytes on the bus (the headline figure:
  cells alone against whole messages, the codec's envelope of ~90 bytes included);
  ``grid_ratio_at_merge_threshold``: the same with grids of the merge threshold's cells (0.2 m,
  the comparison made while robot maps were quantised at the threshold, 16 times fewer cells).
  Two more views of the same maps: ``grid_ratio_msg`` adds to each grid the fixed
  fields of a ROS 1 ``nav_msgs/OccupancyGrid`` (:data:`ROS_GRID_OVERHEAD` bytes): message
  against message; ``grid_ratio_body`` compares the cells with the wireframe part of each
  payload only (``mean_map_body_bytes``; ``mean_grid_bytes`` per publish). Poses are not map
  traffic and are counted apart (``pose_bytes_per_s_per_robot``);
* ``fused_recall``, ``fused_precision``, ``fused_mean_dist_m``: :func:`mapping.metrics.evaluate`
  of the final fused map against the world's truth on a grid of the merge threshold (as the
  paper scores maps; :func:`agents.fleet.fusion.merge_threshold_of`). Replay robots loop
  their recording during the window and jump to its last frame when the window ends (SIGUSR1),
  so the evaluated fused map holds their complete recorded maps; filter robots' maps are
  whatever they mapped by then (at ``--rate`` scans per second);
* ``maps_published``: valid map payloads that reached the bus during the whole run (seen by the
  observer), ``maps_sent``: what the robots report they put, ``maps_merged``: what the fusion
  service took in (:func:`agents.bench.common.merge_counts`).

**Fusion tree** (``--fusers K,K,...``, each count measured in turn for every size, in the same
run): K >= 2 starts K regional fusers over the fold's subtrees and a root instead of one service
(:mod:`agents.bench.tree`); the latency is then end to end through the root, and the entry adds
``regional_ms_p50/p99`` (robot publish -> partial publish), ``root_ms_p50/p99`` (partial publish
-> fused publish), ``fuser_cpu`` (each fuser's share of a core), ``link_bytes_per_s`` (payload
bytes per hop: robots -> regional fusers, partials -> root, fused maps -> clients; the same hops
are reported for one fuser), ``fused_exact`` and, with ``--kill-fuser S``, ``fuser_stall_s``.
``load_avg`` is the machine's load average at the end of each window. ``--synthetic`` replays
synthetic robots instead of recorded filter runs (cheap for 64 robots; see :mod:`agents.bench.tree`).

Filter robots run with their visualisation stream off (``--viz-rate 0``), like replay robots.
The fusion service runs without a Rerun recording unless ``--record``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

from agents.argtypes import non_negative_int
from agents.bench.common import (
    DEFAULT_CACHE,
    DEFAULT_OVERLAP,
    DEFAULT_PARTICLES,
    DEFAULT_RESOLUTION,
    BusObserver,
    LatencyHarvest,
    Procs,
    fleet_routes,
    grid_bytes,
    merge_counts,
    percentile,
    print_table,
    read_state,
    recordings_for,
    rounded,
    sleep_checked,
    wait_for,
)
from agents.errors import UserError
from agents.fleet.proc import cpu_seconds
from wire_codec import MAX_ROBOTS

HELP = "fleet latency, bandwidth and fused-map quality by fleet size"
FLEET = "bench"
LATENCY_TARGET_MS = 50.0
GRID_RATIO_TARGET = 100.0
# A ROS 1 nav_msgs/OccupancyGrid message besides its cells: Header (seq 4, stamp 8, frame_id
# 4 + 3 for "map"), MapMetaData (map_load_time 8, resolution 4, width 4, height 4, origin pose
# 7 x 8) and the data array's length prefix (4).
ROS_GRID_OVERHEAD = 4 + 8 + 4 + 3 + 8 + 4 + 4 + 4 + 7 * 8 + 4


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robots", default="1,2,4,8,16", metavar="N,N,...",
                        help="fleet sizes (default 1,2,4,8,16)")
    parser.add_argument("--duration", type=float, default=20.0, metavar="S",
                        help="measured seconds per size (default 20)")
    parser.add_argument("--rate", type=float, default=10.0, metavar="HZ",
                        help="maps (scans) per second per robot (default 10)")
    parser.add_argument("--world", default="paper-small", metavar="NAME|FILE",
                        help="world (default paper-small)")
    parser.add_argument("--seed", type=non_negative_int, default=0,
                        help="seed of the routes and filters (default 0)")
    parser.add_argument(
        "--filter-upto", type=int, default=2, metavar="N",
        help="sizes up to N run real filter robots (default 2)"
    )
    parser.add_argument("--particles", type=int, default=DEFAULT_PARTICLES,
                        help="particles per filter (default 5)")
    parser.add_argument("--warmup", type=float, default=2.0, metavar="S",
                        help="seconds before the window (default 2)")
    parser.add_argument("--cache", default=str(DEFAULT_CACHE), metavar="DIR",
                        help="recordings cache (default out/bench-cache)")
    parser.add_argument("--out", metavar="DIR",
                        help="keep logs and stores here (default: a temporary directory)")
    parser.add_argument("--record", action="store_true",
                        help="the fusion service also writes a Rerun recording")
    parser.add_argument(
        "--resolution", type=float, default=DEFAULT_RESOLUTION, metavar="M",
        help=f"quantisation step of the robots' maps (default {DEFAULT_RESOLUTION:g})",
    )
    parser.add_argument(
        "--threshold", type=float, metavar="M",
        help="merge threshold of the filters and the fusion (default 0.2, 0.4 for worlds over 100 m)",
    )
    parser.add_argument(
        "--separate-replay", action="store_true",
        help="one process per replay robot (default: all replay robots in one process, one session each)",
    )
    parser.add_argument(
        "--fusers", default="1", metavar="K,K,...",
        help="fusion processes per size, each measured in turn: 1 = the one-process service, K >= 2 = "
        "K regional fusers over the fold's subtrees and a root (agents.bench.tree; default 1)",
    )
    parser.add_argument(
        "--synthetic", action="store_true",
        help="replay robots from synthetic maps (views of the true walls, agents.bench.tree) "
        "instead of recorded filter runs",
    )
    parser.add_argument(
        "--kill-fuser", type=float, metavar="S",
        help="with --fusers K >= 2: kill -9 the regional fuser g1 S seconds into the window; "
        "reports the longest gap in g1's partial publishes (the takeover's stall, fuser_stall_s)",
    )
    parser.add_argument(
        "--fuse-interval", type=float, default=0.0, metavar="S",
        help="every fuser's --min-interval: fuse at most this often, batching the maps that arrive "
        "meanwhile (default 0: fuse after every take)",
    )
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")


def parse_sizes(text: str) -> list[int]:
    try:
        sizes = [int(s) for s in str(text).split(",") if s.strip()]
    except ValueError:
        raise UserError(f"--robots must be a comma-separated list of fleet sizes, got {text!r}") from None
    if not sizes or any(not 1 <= n <= MAX_ROBOTS for n in sizes):
        raise UserError(f"--robots: every size must be between 1 and {MAX_ROBOTS}, got {text!r}")
    return sizes


def _grid_totals(kept: list[tuple[str, bytes]], threshold: float) -> dict[str, int]:
    """Over the window's valid map payloads: ``grid`` (occupancy-grid cells, one byte each, of
    each map's bounding box at its resolution), ``grid_thr`` (the same at the merge
    ``threshold``), ``grid_msg`` (``grid`` plus a ROS 1 ``nav_msgs/OccupancyGrid`` message's
    fixed fields, :data:`ROS_GRID_OVERHEAD`), ``body`` (the wireframe part of each payload: its
    bytes minus those of the same message with an empty map, i.e. without the codec's
    envelope) and ``maps``."""
    from mapping.wireframe import Wireframe
    from wire_codec import decode, encode
    from wire_codec.errors import CodecError

    out = {"grid": 0, "grid_thr": 0, "grid_msg": 0, "body": 0, "maps": 0}
    empty = Wireframe.empty()
    for _rid, data in kept:
        try:
            m = decode(data)
        except CodecError:  # a CRC-valid payload can still be forged (bench hostile's attacker)
            continue
        g = grid_bytes(m.wireframe, m.resolution)
        out["grid"] += g
        out["grid_thr"] += grid_bytes(m.wireframe, threshold)
        out["grid_msg"] += g + ROS_GRID_OVERHEAD
        out["body"] += len(data) - len(encode(dataclasses.replace(m, wireframe=empty)))
        out["maps"] += 1
    return out


def _fused_quality(store: Path, world: Any) -> dict[str, Any]:
    """The stored fused map against the truth, scored on a grid of the merge threshold."""
    from agents.fleet.fusion import merge_threshold_of
    from mapping.metrics import evaluate
    from wire_codec import decode

    out: dict[str, Any] = {"fused_recall": 0.0, "fused_precision": 0.0, "fused_mean_dist_m": None,
                           "fused_vertices": 0, "fused_edges": 0, "fused_version": 0}
    try:
        m = decode((store / "fused.wfm").read_bytes())
    except (OSError, ValueError):
        return out
    wf = m.wireframe
    out.update({"fused_vertices": wf.n_vertices, "fused_edges": wf.n_edges, "fused_version": int(m.seq)})
    if wf.n_edges:
        q = evaluate(world.truth, wf, merge_threshold_of(m))
        out.update({
            "fused_recall": rounded(q["wall_recall"], 4),
            "fused_precision": rounded(q["wall_precision"], 4),
            "fused_mean_dist_m": rounded(q["mean_dist_m"], 4),
        })
    return out


def _sent_counts(d: Path, ids: list[str], mode: str) -> int:
    """Maps the robots say they put: replay logs (``M`` lines) or the agents' status files."""
    total = 0
    for rid in ids:
        if mode == "replay":
            try:
                total += sum(
                    1 for ln in (d / "sent" / f"{rid}.log").read_text().splitlines() if ln.startswith("M ")
                )
            except OSError:
                pass
        else:
            try:
                total += int(json.loads((d / "status" / f"{rid}.json").read_text()).get("maps_sent", 0))
            except (OSError, ValueError, TypeError):
                pass
    return total


def _share(c0: float | None, c1: float | None, wall: float) -> float | None:
    """CPU seconds between two readings over ``wall`` seconds (None when one is missing)."""
    return None if c0 is None or c1 is None else rounded((c1 - c0) / wall, 4)


def _cpu_total(procs: Procs, names: list[str]) -> float | None:
    """CPU seconds of the processes ``names`` together (None when one is gone)."""
    total = 0.0
    for name in names:
        c = cpu_seconds(procs.pid(name))
        if c is None:
            return None
        total += c
    return total


# Over 120 lines: one fleet size measured top to bottom (start, warm up, measure, stop, score),
# its phases sharing the process table and the counters; not yet split into steps.
def run_size(
    n: int,
    args: argparse.Namespace,
    world: Any,
    workdir: Path,
    say: Any,
    fusers: int = 1,
    extra: list[str] | None = None,
) -> dict[str, Any]:
    """One fleet of ``n`` robots: start, measure, stop; returns the size's JSON entry.
    ``fusers`` >= 2: a fusion tree (:mod:`agents.bench.tree`) instead of one service.

    ``extra``: the argv of one more process (``bench hostile``'s attacker; the bus flags are
    appended), started once every robot's first map is on the bus; latency samples of 0 ms
    (its maps, stamped ahead) are then left out, and the entry also gets the fusion service's
    ``rss_kb`` before the extra process starts and at the window's end, and its counters."""
    from agents.bench.tree import LinkCounter, level_latencies, start_tree, synthetic_recordings
    from agents.files.io import write_json
    from agents.fleet.bus import free_port, tcp_endpoint
    from agents.fleet.robot import start_pose_of

    d = workdir / (f"n{n}" if fusers == 1 else f"n{n}-f{fusers}")
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    mode = "filter" if n <= args.filter_upto else "replay"
    ids = [f"r{k + 1}" for k in range(n)]
    thr = args.merge_threshold
    if mode == "replay" and args.synthetic:
        recs = synthetic_recordings(args.world, n, args.seed, args.cache, args.resolution)
    elif mode == "replay":
        recs = recordings_for(
            args.world, n, args.seed, args.cache, args.particles, DEFAULT_OVERLAP, args.resolution, say, thr
        )
    else:
        routes = fleet_routes(world, n, args.seed, DEFAULT_OVERLAP)
        for rid, r in zip(ids, routes):
            write_json(d / "routes" / f"{rid}.json", {"route": r.tolist()})
    ep = tcp_endpoint(free_port())
    bus = ["--connect", ep, "--fleet", FLEET, "--parent-pid", str(os.getpid())]
    store = d / "store"
    # the robots' processes: filter robots one each; replay robots all in one process (one
    # Zenoh session, token and key per robot) unless --separate-replay
    groups = [[r] for r in ids] if mode == "filter" or args.separate_replay else [ids]
    gname = {r: (r if len(g) == 1 else "replay") for g in groups for r in g}
    names = sorted(set(gname.values()))
    result: dict[str, Any] = {
        "robots_mode": mode,
        "robot_processes": len(groups),
        "replay_processes": len(groups) if mode == "replay" else 0,
        "map_resolution_m": args.resolution,
        "merge_threshold_m": thr,
    }
    with Procs(d / "logs") as procs:
        procs.start("router", ["-m", "agents", "router", "--listen", ep])
        with BusObserver(ep, FLEET, timeout=60.0) as obs:
            if fusers == 1:
                fuse = ["-m", "agents", "fuse", *bus, "--store", str(store), "--threshold", repr(thr),
                        "--min-interval", repr(args.fuse_interval)]
                if args.record:
                    fuse += ["--rrd", str(d / "recording.rrd"), "--world", args.world]
                procs.start("fuse", fuse)
                procs.wait_log("fuse", "fusion service ready", 90.0)
                fnames = ["fuse"]
            else:
                fnames = start_tree(procs, fusers, ids, bus, d, thr, args.fuse_interval)
            links = LinkCounter(obs.session, f"wiremap/{FLEET}")
            for group in groups:
                if mode == "replay":
                    argv = ["-m", "agents.bench.replay_robot"]
                    for rid in group:
                        argv += ["--id", rid, "--recording", str(recs[ids.index(rid)])]
                    argv += ["--rate", str(args.rate), "--log", str(d / "sent" / "{id}.log"),
                             "--seed", str(args.seed), *bus]
                else:
                    (rid,) = group
                    k = ids.index(rid)
                    s0 = start_pose_of(routes[k])
                    argv = ["-m", "agents", "robot", "--id", rid, "--world", args.world,
                            "--start", f"{s0.x:.9f},{s0.y:.9f},{s0.theta:.9f}",
                            "--route", str(d / "routes" / f"{rid}.json"), "--rate", str(args.rate),
                            "--seed", str(args.seed + k + 1), "--particles", str(args.particles),
                            "--resolution", repr(float(args.resolution)), "--threshold", repr(thr),
                            "--viz-rate", "0", "--status-file", str(d / "status" / f"{rid}.json"), *bus]
                procs.start(gname[group[0]], argv)
            wait_for(procs, lambda: set(ids) <= obs.seen(), 60.0 + 2.0 * n, "every robot's first map")
            rss0 = obs.fusion_stats().get("rss_kb") if extra is not None else None  # before the extra process
            if extra is not None:
                procs.start("extra", [*extra, *bus])
            sleep_checked(procs, args.warmup)
            harvest = LatencyHarvest(store)
            pid_r = procs.pid("router")
            f0 = {f: cpu_seconds(procs.pid(f)) for f in fnames}
            c0, r0 = _cpu_total(procs, fnames), cpu_seconds(pid_r)
            b0 = _cpu_total(procs, names)
            t0, w0 = time.monotonic(), time.time_ns()
            obs.start_window(keep=True)
            links.on = True
            killed_at = None
            while (left := t0 + args.duration - time.monotonic()) > 0:
                if fusers > 1 and args.kill_fuser is not None and killed_at is None:
                    due = t0 + args.kill_fuser - time.monotonic()
                    if due <= 0:
                        os.kill(procs.pid("g1"), signal.SIGKILL)
                        killed_at = time.monotonic()
                        say(f"killed g1 (pid {procs.pid('g1')}) with SIGKILL")
                        procs.procs.pop("g1").wait()  # reaped: the run goes on without it
                        fnames = [f for f in fnames if f != "g1"]
                        continue
                    left = min(left, due)
                sleep_checked(procs, min(1.0, left))
                harvest.poll()
            win = obs.end_window()
            links.on = False
            t1, w1 = time.monotonic(), time.time_ns()
            end_stats = obs.fusion_stats()
            if extra is not None:
                procs.stop(["extra"], 10.0)
            transport = end_stats.get("transport_ms") or {}
            c1, r1 = _cpu_total(procs, fnames), cpu_seconds(pid_r)
            f1 = {f: cpu_seconds(procs.pid(f)) for f in fnames}
            stall = links.max_gap("g1", killed_at - 1.0, t1) if killed_at is not None else None
            root_stats = obs.fusion_stats() if fusers > 1 else {}
            b1 = _cpu_total(procs, names)
            kept = obs.kept
            if mode == "replay":
                t_sig = time.monotonic()
                procs.signal(names, signal.SIGUSR1)

                def finals() -> bool:
                    snap = obs.snapshot()
                    return all((c := snap.get(r)) is not None and (c.last_map or 0) > t_sig for r in ids)

                wait_for(procs, finals, 15.0, "the robots' final maps")
            procs.stop(names, 15.0)
            time.sleep(0.5)  # the robots' last maps reach the fusion service's queue
            procs.stop([f for f in fnames if f != "root"], 60.0)
            time.sleep(0.3 if fusers > 1 else 0.0)
            procs.stop(["root"] if fusers > 1 else [], 30.0)
            total = obs.snapshot()
            links.close()
        procs.stop(["router"], 10.0)
    harvest.poll()
    state = read_state(store)
    stats = state.get("stats") or {}
    lat = harvest.between(w0, w1)  # fused publishes within the window
    if extra is not None:
        lat = [v for v in lat if v > 0.0]
        result.update({"rss_kb_start": rss0, "rss_kb_end": end_stats.get("rss_kb"), "fusion_counters": stats})
    wall = max(t1 - t0, 1e-9)
    map_bytes = sum(c.map_bytes for c in win.values())
    pose_bytes = sum(c.pose_bytes for c in win.values())
    maps_in_window = sum(c.valid for c in win.values())
    grids = _grid_totals(kept, thr)
    grid = grids["grid"]
    kept_bytes = sum(len(d) for _r, d in kept)
    counts = merge_counts(stats)
    result.update({
        "latency_ms_p50": rounded(percentile(lat, 50)),
        "latency_ms_p99": rounded(percentile(lat, 99)),
        "latency_ms_max": rounded(max(lat) if lat else None),
        "latency_samples": len(lat),
        "transport_ms_p50": rounded(transport.get("p50")),
        "transport_ms_p99": rounded(transport.get("p99")),
        "fusion_cpu_share": rounded((c1 - c0) / wall if c0 is not None and c1 is not None else None, 4),
        "router_cpu_share": rounded((r1 - r0) / wall if r0 is not None and r1 is not None else None, 4),
        "robots_cpu_share": rounded((b1 - b0) / wall if b0 is not None and b1 is not None else None, 4),
        "bytes_per_s_per_robot": rounded(map_bytes / wall / n, 1),
        "pose_bytes_per_s_per_robot": rounded(pose_bytes / wall / n, 1),
        "grid_bytes_per_s_per_robot": rounded(grid / wall / n, 1),
        "grid_ratio": rounded(grid / map_bytes if map_bytes else None, 2),
        # the same maps as grids of the merge threshold's cells (0.2 m: the comparison before
        # robot maps were quantised at 0.05 m)
        "grid_ratio_at_merge_threshold": rounded(grids["grid_thr"] / map_bytes if map_bytes else None, 2),
        "grid_ratio_msg": rounded(grids["grid_msg"] / kept_bytes if kept_bytes else None, 2),
        "grid_ratio_body": rounded(grid / grids["body"] if grids["body"] else None, 2),
        "mean_map_body_bytes": rounded(grids["body"] / grids["maps"] if grids["maps"] else None, 1),
        "mean_grid_bytes": rounded(grid / grids["maps"] if grids["maps"] else None, 1),
        "maps_per_s_per_robot": rounded(maps_in_window / wall / n, 2),
        "mean_map_bytes": rounded(map_bytes / max(1, sum(c.maps for c in win.values())), 1),
    })
    result.update(_fused_quality(store, world))
    if fusers > 1:
        reg = level_latencies(d, fnames, w0, w1)["regional"]
        rs = (root_stats.get("stats") or {}).get("root_ms") or {}
        result.update({
            "regional_ms_p50": rounded(percentile(reg, 50)),
            "regional_ms_p99": rounded(percentile(reg, 99)),
            "root_ms_p50": rounded(rs.get("p50")),
            "root_ms_p99": rounded(rs.get("p99")),
            "fused_exact": root_stats.get("exact"),
        })
    result.update({
        "fusers": fusers,
        "fuser_cpu": {f: _share(f0[f], f1[f], wall) for f in fnames},
        "link_bytes_per_s": {h: rounded(b / wall, 1) for h, b in links.bytes.items()},
        "load_avg": [round(v, 2) for v in os.getloadavg()],
        "fuser_stall_s": rounded(stall, 3) if fusers > 1 and args.kill_fuser is not None else None,
    })
    result.update({
        "maps_sent": _sent_counts(d, ids, mode),
        "maps_published": sum(c.valid for c in total.values()),
        "maps_merged": counts["merged"],
        "maps_arrived": counts["arrived"],
        "maps_dropped": counts["dropped"],
        "window_s": round(wall, 3),
    })
    return result


def run(args: argparse.Namespace) -> int:
    from agents.sim.world import load_world

    sizes = parse_sizes(args.robots)
    for name, v in (("--duration", args.duration), ("--rate", args.rate)):
        if not (math.isfinite(v) and v > 0):
            raise UserError(f"{name} must be a positive number, got {v}")
    for name, v in (("--warmup", args.warmup), ("--fuse-interval", args.fuse_interval)):
        if not (math.isfinite(v) and v >= 0):
            raise UserError(f"{name} must be >= 0, got {v}")
    if args.particles < 1:
        raise UserError(f"--particles must be >= 1, got {args.particles}")
    for name, v in (("--resolution", args.resolution), ("--threshold", args.threshold)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise UserError(f"{name} must be a positive number of metres, got {v}")
    world = load_world(args.world)
    from agents.mapping_run import default_merge_threshold

    args.merge_threshold = (
        float(args.threshold) if args.threshold is not None else default_merge_threshold(world)
    )

    def say(text: str) -> None:
        print(f"bench fleet: {text}", flush=True)

    tmp = None
    if args.out:
        workdir = Path(args.out)
        workdir.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.mkdtemp(prefix="wiremap-bench-fleet-")
        workdir = Path(tmp)
    results: dict[str, Any] = {}
    try:
        fuser_counts = [int(k) for k in str(args.fusers).split(",") if k.strip()]
    except ValueError:
        raise UserError(f"--fusers must be a comma-separated list of counts, got {args.fusers!r}") from None
    if not fuser_counts or any(k < 1 for k in fuser_counts):
        raise UserError(f"--fusers: counts must be >= 1, got {args.fusers!r}")
    try:
        for n in sizes:
            for k in fuser_counts:
                say(f"{n} robot(s), {k} fuser(s) for {args.duration:g} s at {args.rate:g} Hz "
                    f"in {world.name} ...")
                results[str(n) if k == 1 else f"{n}/f{k}"] = run_size(n, args, world, workdir, say, k)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    head = ["robots", "fusers", "mode", "p50_ms", "p99_ms", "in_p99", "fuse_cpu", "B/s/robot", "grid_B/s",
            "ratio", "r_msg", "r_body", "r_thr", "recall", "mean_m", "published", "merged"]
    rows = [
        [n.split("/")[0], r["fusers"], r["robots_mode"], r["latency_ms_p50"], r["latency_ms_p99"],
         r["transport_ms_p99"], r["fusion_cpu_share"],
         r["bytes_per_s_per_robot"], r["grid_bytes_per_s_per_robot"], r["grid_ratio"], r["grid_ratio_msg"],
         r["grid_ratio_body"], r["grid_ratio_at_merge_threshold"], r["fused_recall"], r["fused_mean_dist_m"],
         r["maps_published"], r["maps_merged"]]
        for n, r in results.items()
    ]
    print_table(head, rows)
    largest = results.get(str(max(sizes))) or list(results.values())[-1]
    trees = [(key, r) for key, r in results.items()]
    if any(r["fusers"] > 1 for _, r in trees):
        print_table(
            ["run", "p50_ms", "p99_ms", "regional_p99", "root_p99", "fuser_cpu", "robots->regional B/s",
             "regional->root B/s", "root->clients B/s", "load"],
            [[key, r["latency_ms_p50"], r["latency_ms_p99"], r.get("regional_ms_p99"), r.get("root_ms_p99"),
              " ".join(f"{f}:{v}" for f, v in r["fuser_cpu"].items()), *r["link_bytes_per_s"].values(),
              r["load_avg"][0]] for key, r in trees],
        )
    p99 = largest["latency_ms_p99"]
    ratios = [r["grid_ratio"] for r in results.values() if r["grid_ratio"] is not None]
    summary = {
        "world": world.name,
        "rate_hz": args.rate,
        "duration_s": args.duration,
        "seed": args.seed,
        "map_resolution_m": args.resolution,
        "merge_threshold_m": args.merge_threshold,
        "fuse_interval_s": args.fuse_interval,
        "sizes": results,
        "targets": {
            "latency_ms_p99_max": LATENCY_TARGET_MS,
            "latency_at_robots": max(sizes),
            "latency_met": None if p99 is None else bool(p99 <= LATENCY_TARGET_MS),
            "grid_ratio_min": GRID_RATIO_TARGET,
            "grid_ratio_met": bool(ratios) and bool(min(ratios) >= GRID_RATIO_TARGET),
            "grid_ratio_msg_min": min(
                (r["grid_ratio_msg"] for r in results.values() if r["grid_ratio_msg"]), default=None
            ),
            "grid_ratio_body_min": min(
                (r["grid_ratio_body"] for r in results.values() if r["grid_ratio_body"]), default=None
            ),
            "grid_ratio_at_merge_threshold_min": min(
                (
                    r["grid_ratio_at_merge_threshold"]
                    for r in results.values()
                    if r["grid_ratio_at_merge_threshold"]
                ),
                default=None,
            ),
        },
    }
    print(
        f"p99 latency at {max(sizes)} robots: {p99} ms (target <= {LATENCY_TARGET_MS:g}); "
        f"grid / wireframe bytes: {min(ratios) if ratios else None} (target >= {GRID_RATIO_TARGET:g})",
        flush=True,
    )
    if args.json:
        print(json.dumps(summary))
    return 0
