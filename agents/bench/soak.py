"""``wiremap bench soak --robots 16 --minutes 10 --corrupt 0.01 [--kill-every S] [--json]``: a long
run with corrupted payloads and robots killed and restarted.

A router process, the fusion service (``wiremap fuse --store``), N replay robots
(:mod:`agents.bench.replay_robot`, maps recorded from real filter runs, one map per tick at
``--rate``; a soak of 16 filters would not fit on two cores) and a bus observer in this process.
Each robot damages a map payload with probability ``--corrupt`` (seeded: robot ``k``'s ``j``-th
start uses seed ``seed * 1000 + 100 * j + k``). Every ``--kill-every`` seconds (default 60) one
robot, in turn ``r1, r2, ...``, is killed with SIGKILL and started again at once with the same
id (a new ``boot``, ``seq`` from 1, its recording from the first frame).

Reported (the JSON keys):

* ``valid_sent`` / ``corrupt_sent``: map payloads the robots put, from their logs (a line
  written right after each ``put``; a SIGKILL can fall between the two, so these may differ
  from what reached the bus by at most one per kill);
* ``valid_published`` / ``corrupt_published``: payloads that reached the bus, as the
  benchmark's own subscriber on ``robots/*/map`` saw them (valid = the codec's CRC holds);
* ``maps_merged``: valid maps the fusion service took in: accepted as that robot's latest, or
  already superseded by a newer map of that robot when it arrived, or a duplicate
  (:func:`agents.bench.common.merge_counts`); ``maps_lost = valid_published - maps_merged``
  (target 0: every valid map that reached the bus was merged);
* ``corrupt_dropped``: map payloads the fusion service received and refused
  (``received - merged``; target: ``corrupt_published``);
* ``fusion_rss_mb_start`` / ``_end`` / ``_max`` / ``_per_min``: the fusion process's RSS
  sampled every second from ``--warmup`` s after every robot's first map to the end, and the
  least-squares slope; ``rss_flat`` means ``end <= start + max(5 MB, 10 % of start)``;
* ``latency_ms_p50`` / ``p99``: publish-to-fused latency over the run (fused publishes after the
  warm-up and before the end), from the fusion service's ``latency.log``, read every second
  (``latency_samples_missed`` counts samples rotated away before a read);
* ``restarts`` / ``restarts_survived``: a restart survives when the fusion service is alive and
  its store holds a map of the robot's new boot (checked until the end of the run).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.argtypes import non_negative_int
from agents.bench.common import (
    DEFAULT_CACHE,
    DEFAULT_OVERLAP,
    DEFAULT_PARTICLES,
    BusObserver,
    LatencyHarvest,
    Procs,
    merge_counts,
    percentile,
    print_table,
    read_state,
    recordings_for,
    rounded,
    rss_bytes,
    sleep_checked,
    wait_for,
)
from agents.errors import UserError
from agents.fleet.proc import cpu_seconds
from wire_codec import MAX_ROBOTS

HELP = "long run with corrupt payloads and robot restarts"
FLEET = "soak"
MB = 1024.0 * 1024.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robots", type=int, default=16, metavar="N", help="robots (default 16)")
    parser.add_argument("--minutes", type=float, default=10.0, metavar="M",
                        help="length of the run (default 10)")
    parser.add_argument("--corrupt", type=float, default=0.01, metavar="P",
                        help="share of damaged payloads (default 0.01)")
    parser.add_argument("--rate", type=float, default=10.0, metavar="HZ",
                        help="maps per second per robot (default 10)")
    parser.add_argument("--kill-every", type=float, default=60.0, metavar="S",
                        help="SIGKILL + restart a robot every S s")
    parser.add_argument("--world", default="paper-small", metavar="NAME|FILE",
                        help="world (default paper-small)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed (default 0)")
    parser.add_argument("--particles", type=int, default=DEFAULT_PARTICLES,
                        help="particles of the recorded filters")
    parser.add_argument("--warmup", type=float, default=2.0, metavar="S",
                        help="seconds before the clock starts (default 2)")
    parser.add_argument("--cache", default=str(DEFAULT_CACHE), metavar="DIR",
                        help="recordings cache (default out/bench-cache)")
    parser.add_argument("--out", metavar="DIR",
                        help="keep logs and the store here (default: a temporary directory)")
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")


def read_sent_log(path: Path) -> dict[str, Any]:
    """A replay robot's log: boots in order, valid and corrupt payload counts."""
    boots: list[int] = []
    valid = corrupt = 0
    try:
        text = path.read_text()
    except OSError:
        return {"boots": boots, "valid": 0, "corrupt": 0}
    for ln in text.splitlines():
        f = ln.split()
        if len(f) >= 2 and f[0] == "B":
            boots.append(int(f[1]))
        elif len(f) == 5 and f[0] == "M":
            if f[3] == "1":
                valid += 1
            else:
                corrupt += 1
    return {"boots": boots, "valid": valid, "corrupt": corrupt}


def rss_slope_mb_per_min(samples: list[tuple[float, int]]) -> float | None:
    if len(samples) < 3:
        return None
    t = np.array([s[0] for s in samples]) / 60.0
    y = np.array([s[1] for s in samples]) / MB
    if np.ptp(t) <= 0:
        return None
    return float(np.polyfit(t, y, 1)[0])


# Over 120 lines: one soak scenario read top to bottom (start, sample, inject faults, restart,
# stop, score), its phases sharing the process table and the samples; not yet split into steps.
def soak(args: argparse.Namespace, world: Any, d: Path, say: Any) -> dict[str, Any]:
    from agents.fleet.bus import free_port, tcp_endpoint
    from agents.mapping_run import default_merge_threshold

    n = args.robots
    ids = [f"r{k + 1}" for k in range(n)]
    recs = recordings_for(args.world, n, args.seed, args.cache, args.particles, DEFAULT_OVERLAP, say=say)
    ep = tcp_endpoint(free_port())
    bus = ["--connect", ep, "--fleet", FLEET, "--parent-pid", str(os.getpid())]
    store = d / "store"
    starts = dict.fromkeys(ids, 0)

    def robot_argv(k: int) -> list[str]:
        rid = ids[k]
        seed = args.seed * 1000 + 100 * starts[rid] + k
        return ["-m", "agents.bench.replay_robot", "--id", rid, "--recording", str(recs[k]), "--rate",
                str(args.rate), "--corrupt", str(args.corrupt), "--seed", str(seed), "--log",
                str(d / "sent" / f"{rid}.log"), *bus]

    rss: list[tuple[float, int]] = []
    restarts: list[dict[str, Any]] = []  # {robot, t, boots_before, survived}
    fusion_alive = True
    with Procs(d / "logs") as procs:
        procs.start("router", ["-m", "agents", "router", "--listen", ep])
        with BusObserver(ep, FLEET, timeout=60.0) as obs:
            thr = default_merge_threshold(world)  # as the recordings' filters
            procs.start("fuse",
                        ["-m", "agents", "fuse", *bus, "--store", str(store), "--threshold", repr(thr)])
            procs.wait_log("fuse", "fusion service ready", 90.0)
            for k in range(n):
                procs.start(ids[k], robot_argv(k))
            wait_for(procs, lambda: set(ids) <= obs.seen(), 60.0 + 2.0 * n, "every robot's first map")
            sleep_checked(procs, args.warmup)
            harvest = LatencyHarvest(store)
            pid_f = procs.pid("fuse")
            c0 = cpu_seconds(pid_f)
            t0, w0 = time.monotonic(), time.time_ns()
            length = args.minutes * 60.0
            next_kill = t0 + args.kill_every
            next_rss = t0
            victim = 0

            def check_restarts() -> None:
                state = read_state(store)
                held = state.get("robots") or {}
                for r in restarts:
                    if r["survived"]:
                        continue
                    boots = read_sent_log(d / "sent" / f"{r['robot']}.log")["boots"]
                    new = boots[r["boots_before"]:]
                    got = (held.get(r["robot"]) or {}).get("boot")
                    if new and got is not None and int(got) in new and procs.alive("fuse"):
                        r["survived"] = True
                        r["merged_after_s"] = round(time.monotonic() - r["t"], 3)

            while True:
                now = time.monotonic()
                if now >= t0 + length:
                    break
                if not procs.alive("fuse"):
                    fusion_alive = False
                    raise UserError(f"the fusion service died (see {procs.log_path('fuse')})")
                dead = [r for r in procs.dead() if r != "fuse"]
                if dead:
                    raise UserError(f"{', '.join(dead)} exited by itself (see {procs.logs})")
                if now >= next_rss:
                    b = rss_bytes(pid_f)
                    if b is not None:
                        rss.append((now - t0, b))
                    next_rss += 1.0
                    check_restarts()
                    harvest.poll()
                if now >= next_kill:
                    next_kill += args.kill_every
                    rid = ids[victim % n]
                    victim += 1
                    before = len(read_sent_log(d / "sent" / f"{rid}.log")["boots"])
                    procs.kill(rid)
                    starts[rid] += 1
                    procs.start(rid, robot_argv(ids.index(rid)))
                    restarts.append({"robot": rid, "t": time.monotonic(), "boots_before": before,
                                     "survived": False})
                    say(f"t={now - t0:.0f} s: killed {rid} (SIGKILL) and started it again")
                time.sleep(max(0.0, min(next_rss, next_kill, t0 + length) - time.monotonic()))
            t1, w1 = time.monotonic(), time.time_ns()
            c1 = cpu_seconds(pid_f)
            b = rss_bytes(pid_f)
            if b is not None:
                rss.append((t1 - t0, b))
            # restarts near the end: give them a few seconds to reach the store
            deadline = time.monotonic() + 10.0
            check_restarts()
            while (any(not r["survived"] for r in restarts) and time.monotonic() < deadline
                   and procs.alive("fuse")):
                time.sleep(0.25)
                check_restarts()
            procs.stop(ids, 15.0)
            time.sleep(0.5)  # the robots' last maps reach the fusion service's queue
            codes = procs.stop(["fuse"], 60.0)
            fusion_alive = fusion_alive and codes.get("fuse") == 0
            total = obs.snapshot()
        procs.stop(["router"], 10.0)
    harvest.poll()
    state = read_state(store)
    stats = state.get("stats") or {}
    counts = merge_counts(stats)
    lat = harvest.between(w0, w1)
    sent = [read_sent_log(d / "sent" / f"{rid}.log") for rid in ids]
    valid_published = sum(c.valid for c in total.values())
    corrupt_published = sum(c.corrupt for c in total.values())
    wall = max(t1 - t0, 1e-9)
    start_mb = rss[0][1] / MB if rss else None
    end_mb = rss[-1][1] / MB if rss else None
    flat = None if start_mb is None or end_mb is None else bool(end_mb <= start_mb + max(5.0, 0.1 * start_mb))
    return {
        "world": world.name,
        "robots": n,
        "minutes": args.minutes,
        "rate_hz": args.rate,
        "corrupt": args.corrupt,
        "seed": args.seed,
        "kill_every_s": args.kill_every,
        "valid_sent": sum(s["valid"] for s in sent),
        "corrupt_sent": sum(s["corrupt"] for s in sent),
        "valid_published": valid_published,
        "corrupt_published": corrupt_published,
        "maps_merged": counts["merged"],
        "maps_lost": valid_published - counts["merged"],
        "corrupt_dropped": counts["dropped"],
        "fusion_arrived": counts["arrived"],
        "fusion_overflow": counts["overflow"],
        "fusion_rate_limited": counts["rate_limited"],
        "fusion_rss_mb_start": rounded(start_mb, 1),
        "fusion_rss_mb_end": rounded(end_mb, 1),
        "fusion_rss_mb_max": rounded(max(s[1] for s in rss) / MB if rss else None, 1),
        "fusion_rss_mb_per_min": rounded(rss_slope_mb_per_min(rss), 3),
        "rss_flat": flat,
        "fusion_cpu_share": rounded((c1 - c0) / wall if c0 is not None and c1 is not None else None, 4),
        "latency_ms_p50": rounded(percentile(lat, 50)),
        "latency_ms_p99": rounded(percentile(lat, 99)),
        "latency_samples": len(lat),
        "latency_samples_missed": harvest.missed,
        "restarts": len(restarts),
        "restarts_survived": sum(1 for r in restarts if r["survived"]),
        "restart_merged_after_s_max": rounded(max((r.get("merged_after_s", 0.0) for r in restarts),
                                                  default=None)),
        "fusion_alive": fusion_alive,
        "fusion_version": int(state.get("version", 0) or 0),
        "window_s": round(wall, 3),
        "all_valid_merged": counts["merged"] == valid_published,
    }


def run(args: argparse.Namespace) -> int:
    from agents.sim.world import load_world

    if not 1 <= args.robots <= MAX_ROBOTS:
        raise UserError(f"--robots must be between 1 and {MAX_ROBOTS}, got {args.robots}")
    for name, v in (("--minutes", args.minutes), ("--rate", args.rate), ("--kill-every", args.kill_every)):
        if not (math.isfinite(v) and v > 0):
            raise UserError(f"{name} must be a positive number, got {v}")
    if not 0.0 <= args.corrupt <= 1.0:
        raise UserError(f"--corrupt must be within [0, 1], got {args.corrupt}")
    if not (math.isfinite(args.warmup) and args.warmup >= 0):
        raise UserError(f"--warmup must be >= 0, got {args.warmup}")
    world = load_world(args.world)

    def say(text: str) -> None:
        print(f"bench soak: {text}", flush=True)

    tmp = None
    if args.out:
        d = Path(args.out)
        if (d / "store").exists():
            shutil.rmtree(d / "store")
        shutil.rmtree(d / "sent", ignore_errors=True)
        d.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.mkdtemp(prefix="wiremap-bench-soak-")
        d = Path(tmp)
    say(f"{args.robots} robots for {args.minutes:g} min at {args.rate:g} Hz, "
        f"{100 * args.corrupt:g} % damaged, "
        f"a SIGKILL + restart every {args.kill_every:g} s, in {world.name}")
    try:
        r = soak(args, world, d, say)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    rows = [
        ["valid maps sent / reached the bus / merged",
         f"{r['valid_sent']} / {r['valid_published']} / {r['maps_merged']}"],
        ["valid maps lost", r["maps_lost"]],
        ["damaged sent / reached the bus / dropped",
         f"{r['corrupt_sent']} / {r['corrupt_published']} / {r['corrupt_dropped']}"],
        ["fusion RSS start / end / max (MB)",
         f"{r['fusion_rss_mb_start']} / {r['fusion_rss_mb_end']} / {r['fusion_rss_mb_max']}"],
        ["fusion RSS slope (MB/min)", r["fusion_rss_mb_per_min"]],
        ["latency p50 / p99 (ms)", f"{r['latency_ms_p50']} / {r['latency_ms_p99']}"],
        ["restarts survived", f"{r['restarts_survived']} / {r['restarts']}"],
        ["fusion CPU share", r["fusion_cpu_share"]],
    ]
    print_table(["soak", "value"], rows)
    if args.json:
        print(json.dumps(r))
    return 0
