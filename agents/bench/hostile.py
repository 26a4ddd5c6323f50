"""``wiremap bench hostile [--robots N] [--duration S] [--messages K] [--json]``: one stolen robot
against the fleet.

Three measurements in one run:

* **In-process crash count** (``crashes``, ``tracebacks``): ``--messages`` (10,000) hostile
  messages of every type (:func:`attacks`) go through what reads them in the fusion service and
  in ``watch``/``run``: robot maps through :meth:`FusionState.offer` (quarantine and work
  budget on, as in the service), poses and scans through :mod:`agents.fleet.validate`, fused
  maps through :func:`agents.fleet.validate.fused_map`. Every exception that escapes is a crash.
  Bit-flipped maps carry a recomputed CRC, so decoding and validation, not the CRC, must catch
  them (``flipped_caught``: refused, quarantined or harmlessly accepted, never a crash). Also
  the cost of one 5,000-vertex map (``map_5000_ms``, target < 50 ms, the first one, cold) and
  the slowest hostile map of each kind (``slowest_ms``).
* **Honest latency quiet vs attacked** (``quiet`` / ``attacked``, side by side): the same fleet
  (:func:`agents.bench.fleet.run_size`, replay robots) twice, the second time with an attacker
  process (``python -m agents.bench.hostile --attack``) publishing every attack in a loop on
  its own robot keys (``r99``) at ``--attack-rate`` messages per second, from the fleet's first
  maps on or ``--attack-after`` seconds later (a fusion service trusts the claimed boot of the
  robots it hears of in its first 3 s: an attacker there may place walls within its claimed
  reach; ``fused_precision`` shows it). The attacker stamps its
  maps 90 s ahead (within the accepted clock skew) so that its own accepted maps' latency
  samples are 0 and are left out (honest samples are never exactly 0): the percentiles are the
  honest robots'. ``p99_ratio`` = attacked p99 / quiet p99 (target <= 2).
* **Fusion RSS growth** under attack (``rss_growth_mb``: ``fused/stats``' ``rss_kb`` at the end
  of the attacked window minus just before the attacker started; target < 50 MB) and the fusion service's
  counters
  (``quarantined``, ``absurd_by``, ...).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import resource
import shutil
import signal
import sys
import tempfile
import time
import traceback
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from agents.argtypes import non_negative_int

HELP = "one stolen robot: crashes over hostile messages, honest latency quiet vs attacked, fusion RSS"
ATTACKER = "r99"
MAP_5000_TARGET_MS = 50.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robots", type=int, default=4, metavar="N",
                        help="honest robots (default 4, replay robots)")
    parser.add_argument("--duration", type=float, default=20.0, metavar="S",
                        help="measured seconds per run (default 20)")
    parser.add_argument("--rate", type=float, default=10.0, metavar="HZ",
                        help="honest maps per second per robot (default 10)")
    parser.add_argument("--attack-rate", type=float, default=40.0, metavar="HZ",
                        help="attacker messages per second (default 40)")  # fmt: skip
    parser.add_argument("--attack-after", type=float, default=0.0, metavar="S",
                        help="the attacker waits S seconds after the fleet's first maps (default 0: at once)")  # fmt: skip  # noqa: E501
    parser.add_argument("--messages", type=non_negative_int, default=10_000, metavar="K",
                        help="in-process hostile messages (default 10000)")
    parser.add_argument("--world", default="paper-small", metavar="NAME|FILE",
                        help="world (default paper-small)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed (default 0)")
    parser.add_argument("--no-fleet", action="store_true", help="only the in-process part (no processes)")
    parser.add_argument("--cache", default=None, metavar="DIR",
                        help="recordings cache (default out/bench-cache)")
    parser.add_argument("--out", metavar="DIR",
                        help="keep logs and stores here (default: a temporary directory)")
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")
    # the attacker process (started by the bench itself)
    parser.add_argument("--attack", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--connect", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--fleet", default="bench", help=argparse.SUPPRESS)
    parser.add_argument("--parent-pid", type=int, default=None, help=argparse.SUPPRESS)


# ---------------------------------------------------------------------- the attacks
def _map(n_or_pts: Any, edges: Any, *, boot: int, seq: int, stamp_ns: int, sender: str = ATTACKER,
         origin: tuple[float, float, float] = (0.0, 0.0, 0.0), meta: dict[str, Any] | None = None) -> bytes:  # fmt: skip  # noqa: E501
    from agents.fleet.fusion import encode_message
    from mapping.se2 import Pose
    from mapping.wireframe import Wireframe
    from wire_codec.message import MapMessage, MessageKind

    wf = Wireframe.build(np.asarray(n_or_pts, dtype=np.float64), np.asarray(edges, dtype=np.int64))
    return encode_message(
        MapMessage(
            kind=MessageKind.ROBOT_MAP, sender=sender, seq=seq, stamp_ns=stamp_ns, pose=Pose.identity(),
            frame=f"odom/{sender}", origin=Pose(*origin), resolution=0.05, wireframe=wf,
            meta={"boot": boot, "t": 1.0, "step": seq, **(meta or {})},
        )
    )  # fmt: skip


def _chain(n: int) -> np.ndarray:
    return np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)


def _budget_map(rng: np.random.Generator, n: int, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` vertices at the budget's limits: a random walk of short walls (at most 16 per
    square metre, well within 5 km) spread within ``reach`` of the start."""
    steps = rng.normal(0.0, 1.0, size=(n, 2))
    pts = np.cumsum(steps, axis=0)
    pts = pts / max(1e-9, float(np.abs(pts).max())) * (0.9 * reach)
    return pts, _chain(n)


def _flip(data: bytes, rng: random.Random, bits: int) -> bytes:
    """``bits`` random bits flipped in the message, the CRC recomputed (so it passes it)."""
    b = bytearray(data)
    for _ in range(bits):
        i = rng.randrange(0, max(1, len(b) - 5))
        b[i] ^= 1 << rng.randrange(8)
    head = bytes(b[:-5])
    return head + bytes([0xCE]) + (zlib.crc32(head) & 0xFFFFFFFF).to_bytes(4, "big")


def attacks(seed: int, boot: int, stamp_ahead_s: float = 0.0) -> Iterator[tuple[str, str, bytes]]:
    """``(kind, key suffix, payload)`` of every attack, forever (a loop over the kinds).

    Maps: 5,000 vertices (over the budget), 3,000 at the budget's limits, a dense stack,
    kilometres of walls, walls beyond reach, a boot from the future, a seq far ahead, a wrong
    sender, junk walls across the fleet's rooms, bit-flipped maps with the CRC recomputed,
    truncated maps, random bytes. Poses: ``t=1e300``, NaN poses, bad statuses, junk msgpack.
    Scans (viz): infinite times, huge arrays, wrong types.
    """
    from agents.fleet.bus import encode_pose
    from mapping.se2 import Pose

    rng = np.random.default_rng(seed)
    prng = random.Random(seed)
    seq = 0
    square = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])
    while True:
        seq += 1
        now = time.time_ns()
        stamp = now + int(stamp_ahead_s * 1e9)
        good = _map(square, [[0, 1], [1, 2], [2, 3], [3, 0]], origin=(1.0, 1.0, 0.0), boot=boot, seq=seq,
                    stamp_ns=stamp)
        yield "map_5000", "map", _map(rng.uniform(-20, 20, (5000, 2)), _chain(5000), boot=boot, seq=seq,
                                      stamp_ns=stamp)
        yield "map_budget", "map", _map(*_budget_map(rng, 3000, 45.0), boot=boot, seq=seq, stamp_ns=stamp)
        yield "map_dense", "map", _map(rng.uniform(0, 1, (2000, 2)), _chain(2000), boot=boot, seq=seq,
                                       stamp_ns=stamp)
        yield "map_km_walls", "map", _map(rng.uniform(-500, 500, (1500, 2)), _chain(1500), boot=boot, seq=seq,
                                          stamp_ns=stamp)
        yield "map_reach", "map", _map(rng.uniform(-600, 600, (3, 2)), _chain(3), boot=boot, seq=seq,
                                       stamp_ns=stamp)
        yield "map_future", "map", _map(square, _chain(4), boot=now + 3600 * 10**9, seq=1, stamp_ns=stamp)
        yield "map_seq_jump", "map", _map(square, _chain(4), boot=boot, seq=seq + 10**9, stamp_ns=stamp)
        yield "map_sender", "map", _map(square, _chain(4), sender="r1", boot=boot, seq=seq, stamp_ns=stamp)
        junk = rng.uniform(0, 40, (400, 2))
        yield "map_junk_rooms", "map", _map(np.concatenate([junk, junk + np.array([1.5, 0.0])]),
                                            np.stack([np.arange(400), np.arange(400, 800)], axis=1), boot=boot, seq=seq, stamp_ns=stamp)  # fmt: skip  # noqa: E501
        yield "map_flipped", "map", _flip(good, prng, prng.randint(1, 8))
        yield "map_truncated", "map", good[: prng.randrange(1, len(good))]
        yield "map_random", "map", rng.bytes(int(rng.integers(1, 4096)))
        pose = msgpack.unpackb(encode_pose(seq=seq, t=1.0, stamp_ns=now, odom=Pose(0, 0, 0),
                                           fleet=Pose(0, 0, 0)), raw=False)
        yield "pose_t_1e300", "pose", msgpack.packb({**pose, "t": 1e300})
        yield "pose_nan", "pose", msgpack.packb({**pose, "fleet": [math.nan, math.inf, 0.0]})
        yield (
            "pose_status",
            "pose",
            msgpack.packb({**pose, "status": {"step": "x", "vertices": -1, "maps_sent": 2**64 - 1}}),
        )
        yield "pose_junk", "pose", rng.bytes(int(rng.integers(1, 512)))
        yield "viz_inf", "viz", msgpack.packb({"t": math.inf, "pose": [0, 0, 0], "scan": {}, "particles": [],
                                               "weights": []})
        yield "viz_types", "viz", msgpack.packb({"t": 1.0, "pose": "x", "scan": [1, 2], "particles": {"a": 1},
                                                 "weights": None})
        yield "viz_huge", "viz", msgpack.packb({"t": 1.0, "pose": [0, 0, 0],
                                                "scan": {"points": b"\0" * 1_000_000}})


# ---------------------------------------------------------------------- in process
def crash_count(messages: int, seed: int) -> dict[str, Any]:
    """Drive ``messages`` hostile messages through every reader; count what escapes."""
    from agents.fleet import validate
    from agents.fleet.fusion import FusionConfig, FusionState
    from agents.fleet.fusion.budget import BudgetConfig, WorkBudget
    from agents.fleet.fusion.quarantine import QuarantineConfig

    st = FusionState(FusionConfig(threshold=0.2), quarantine=QuarantineConfig())
    st.budget = WorkBudget(BudgetConfig())
    boot = time.time_ns() - 600 * 10**9  # the attacker has been up for 10 minutes (reach 1,850 m)
    honest = _map([[0.0, 0.0], [6.0, 0.0], [6.0, 6.0], [0.0, 6.0]], [[0, 1], [1, 2], [2, 3], [3, 0]],
                  boot=boot, seq=1, stamp_ns=time.time_ns(), sender="r1")  # fmt: skip
    st.offer(honest, "r1", time.time_ns())
    st.fuse()
    crashes: list[str] = []
    slowest: dict[str, float] = {}
    counts: dict[str, int] = {}
    flipped = {"n": 0, "refused": 0, "accepted": 0}
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    first_5000: float | None = None
    for i, (kind, suffix, data) in enumerate(attacks(seed, boot)):
        if i >= messages:
            break
        counts[kind] = counts.get(kind, 0) + 1
        t0 = time.perf_counter()
        try:
            if suffix == "map":
                ok = st.offer(data, ATTACKER, time.time_ns())
                if kind == "map_flipped":
                    flipped["n"] += 1
                    flipped["accepted" if ok else "refused"] += 1
                if i % 50 == 0:
                    st.release_held(time.time_ns())
                    st.fuse()
                try:  # the fused map as watch and run read it
                    validate.fused_map(_flip(data, random.Random(i), 2)) if kind == "map_flipped" else None
                except validate.Invalid:
                    pass
            elif suffix == "pose":
                try:
                    validate.pose(data)
                except validate.Invalid:
                    pass
            else:
                try:
                    validate.viz(data)
                except validate.Invalid:
                    pass
        except Exception:  # what the bench counts
            crashes.append(f"{kind}: {traceback.format_exc(limit=3)}")
        ms = 1000 * (time.perf_counter() - t0)
        if kind == "map_5000" and first_5000 is None:
            first_5000 = ms
        slowest[kind] = max(slowest.get(kind, 0.0), ms)
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "messages": sum(counts.values()),
        "kinds": len(counts),
        "crashes": len(crashes),
        "tracebacks": crashes[:3],
        "map_5000_ms": round(first_5000 or 0.0, 3),
        "slowest_ms": {k: round(v, 2) for k, v in sorted(slowest.items())},
        "flipped": flipped,
        "peak_rss_growth_mb": round((rss1 - rss0) / 1024, 1),
        "state_stats": {k: v for k, v in st.stats.as_dict(False).items() if k.endswith("_by") or k in (
            "received", "accepted", "malformed", "rejected", "absurd", "quarantined", "held")},
    }


# ---------------------------------------------------------------------- the attacker process
def attack_loop(args: argparse.Namespace) -> int:
    """Publish every attack in a loop on ``r99``'s keys until SIGTERM (or the parent goes)."""
    from agents.fleet.bus import FleetKeys, build_config, open_session

    keys = FleetKeys(args.fleet)
    stop = {"now": False}
    signal.signal(signal.SIGTERM, lambda *_: stop.update(now=True))
    session = open_session(build_config("client", None, [args.connect]), timeout=30.0)
    if session is None:
        return 1
    boot = time.time_ns() - 600 * 10**9
    period = 1.0 / max(1e-3, args.attack_rate)
    t_wait = time.monotonic() + args.attack_after
    while time.monotonic() < t_wait and not stop["now"]:
        time.sleep(0.1)
    sent = 0
    try:
        nxt = time.monotonic()
        for _kind, suffix, data in attacks(args.seed, boot, stamp_ahead_s=90.0):
            if stop["now"] or (args.parent_pid and not _alive(args.parent_pid)):
                break
            key = {"map": keys.robot_map, "pose": keys.robot_pose, "viz": keys.robot_viz}[suffix](ATTACKER)
            session.put(key, data)
            sent += 1
            nxt += period
            time.sleep(max(0.0, nxt - time.monotonic()))
    finally:
        session.close()
    print(f"attacker sent {sent} messages", flush=True)
    return 0


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except OSError:
        return False
    return True


# ---------------------------------------------------------------------- the fleet part
def _fleet_args(args: argparse.Namespace) -> argparse.Namespace:
    from agents.bench import fleet
    from agents.bench.common import DEFAULT_CACHE

    p = argparse.ArgumentParser()
    fleet.add_arguments(p)
    fa = p.parse_args([])
    fa.duration, fa.rate, fa.world, fa.seed = args.duration, args.rate, args.world, args.seed
    fa.cache = args.cache or str(DEFAULT_CACHE)
    fa.filter_upto = 0  # replay robots: the attack, not two cores' filters, is what is measured
    return fa


def _run(
    n: int, fa: argparse.Namespace, world: Any, workdir: Path, attacker: bool, say: Any
) -> dict[str, Any]:
    from agents.bench import fleet

    argv = None
    if attacker:
        argv = ["-m", "agents.bench.hostile", "--attack", "--attack-rate", str(fa.attack_rate), "--seed",
                str(fa.seed), "--attack-after", str(fa.attack_after)]
    r = fleet.run_size(n, fa, world, workdir / ("attacked" if attacker else "quiet"), say, extra=argv)
    keep = ("latency_ms_p50", "latency_ms_p99", "latency_ms_max", "latency_samples", "fusion_cpu_share",
            "fused_recall", "fused_precision", "fused_mean_dist_m", "rss_kb_start", "rss_kb_end", "fusion_counters")  # fmt: skip  # noqa: E501
    return {k: r.get(k) for k in keep}


def run(args: argparse.Namespace) -> int:
    if args.attack:
        return attack_loop(args)
    from agents.mapping_run import default_merge_threshold
    from agents.sim.world import load_world

    def say(text: str) -> None:
        print(f"bench hostile: {text}", flush=True)

    say(f"in process: {args.messages} hostile messages ...")
    t0 = time.monotonic()
    inproc = crash_count(args.messages, args.seed)
    say(
        f"  {inproc['crashes']} crashes, 5,000-vertex map {inproc['map_5000_ms']} ms, {time.monotonic() - t0:.1f} s"  # noqa: E501
    )
    for tb in inproc["tracebacks"]:
        print(tb, file=sys.stderr)
    out: dict[str, Any] = {"bench": "hostile", **inproc, "load_avg": os.getloadavg()[0]}
    if not args.no_fleet:
        world = load_world(args.world)
        fa = _fleet_args(args)
        fa.merge_threshold = default_merge_threshold(world)
        fa.attack_rate = args.attack_rate
        fa.attack_after = args.attack_after
        fa.warmup = max(fa.warmup, args.attack_after)  # the window starts once the attack has
        tmp = None
        if args.out:
            workdir = Path(args.out)
            workdir.mkdir(parents=True, exist_ok=True)
        else:
            tmp = tempfile.mkdtemp(prefix="wiremap-bench-hostile-")
            workdir = Path(tmp)
        try:
            say(f"{args.robots} honest robots, quiet, {args.duration:g} s ...")
            quiet = _run(args.robots, fa, world, workdir, False, say)
            say(
                f"{args.robots} honest robots and an attacker at {args.attack_rate:g} msg/s, {args.duration:g} s ..."  # noqa: E501
            )
            attacked = _run(args.robots, fa, world, workdir, True, say)
        finally:
            if tmp is not None:
                shutil.rmtree(tmp, ignore_errors=True)
        q99, a99 = quiet.get("latency_ms_p99"), attacked.get("latency_ms_p99")
        rs, re_ = attacked.get("rss_kb_start"), attacked.get("rss_kb_end")
        out.update({
            "robots": args.robots,
            "quiet": quiet,
            "attacked": attacked,
            "p99_ratio": round(a99 / q99, 2) if q99 and a99 is not None else None,
            "rss_growth_mb": round((re_ - rs) / 1024, 1) if rs is not None and re_ is not None else None,
        })  # fmt: skip
        out["load_avg_end"] = os.getloadavg()[0]
    targets = {
        "crashes_0": out["crashes"] == 0,
        "map_5000_under_50ms": out["map_5000_ms"] < MAP_5000_TARGET_MS,
    }
    if "p99_ratio" in out:
        targets["p99_at_most_2x"] = out["p99_ratio"] is not None and out["p99_ratio"] <= 2.0
        targets["rss_growth_under_50mb"] = out["rss_growth_mb"] is not None and out["rss_growth_mb"] < 50.0
    out["targets"] = targets
    print(json.dumps(out, sort_keys=True, indent=None if args.json else 1))
    return 0 if all(targets.values()) else 1


if __name__ == "__main__":  # the attacker process: python -m agents.bench.hostile --attack ...
    _p = argparse.ArgumentParser()
    add_arguments(_p)
    raise SystemExit(run(_p.parse_args()))
