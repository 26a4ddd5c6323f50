"""CPU per robot map in the fusion's intake, as the service runs it (``python -m
tests.intake_cpu [--robots 64] [--rounds 80]``; two checkouts side by side in one run:
``python tests/intake_cpu.py --compare OLD,NEW [--runs 3]``).

The fleet of ``wiremap bench fleet --synthetic``: ``--robots`` synthetic museum robots
(:func:`agents.bench.tree.synthetic_recordings`), every robot sending every round (10 Hz,
rounds 0.1 s apart), robot ``k``'s ``j``-th map its recording's frame ``(j + k) mod frames``
(they loop, as the bench's replay robots do: the robots whose recording has one frame send the
same map every time). Each round is one drained batch: each robot's payload goes through
:meth:`FusionState.offer_latest` with the clock and the quarantine on (as the service), then a
fast fuse (``max_realign=0``) and one ``realign(limit=1)``, as the service's loop does. The
first ``--warm`` rounds are not counted.

Prints the thread-time milliseconds per map taken in (``offer_latest``), split by outcome:
``changed`` (the robot's map changed), ``same`` (accepted, same content as the robot's last
map: a re-sent map), ``dropped`` (refused or quarantined); the fuse's milliseconds per round;
and a hash of every fused map and the counters (two checkouts take and fuse alike exactly when
the hashes agree). ``--profile`` adds cProfile's top 30 over the counted offers.

``--compare OLD,NEW`` runs this file ``--runs`` times under each checkout (``PYTHONPATH``),
alternated, and prints each run's line and the medians side by side; the file uses nothing
newer than issue 21's start, so it runs against older checkouts. A development measurement
(figures in ``docs/experiments.md``), not one of ``wiremap bench``'s benchmarks.
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import json
import os
import pstats
import statistics
import subprocess
import sys
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=80)
    ap.add_argument("--warm", type=int, default=10)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--json", action="store_true", help="one JSON line (for --compare)")
    ap.add_argument("--compare", default=None, metavar="OLD,NEW")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    if args.compare:
        compare(args)
        return
    out = run(args.robots, args.rounds, args.warm, args.profile)
    if args.json:
        print(json.dumps(out))
    else:
        print(line(out))


def line(o: dict) -> str:
    return (f"{o['robots']} robots, {o['maps']} maps: {o['ms_per_map']:.3f} ms per map (changed "
            f"{o['ms_changed']:.3f} x {o['n_changed']}, same {o['ms_same']:.3f} x {o['n_same']}, dropped "
            f"{o['ms_dropped']:.3f} x {o['n_dropped']}); fuse {o['ms_fuse']:.2f} ms per round; "
            f"hash {o['hash']}")


def run(n: int, rounds: int, warm: int, profile: bool) -> dict:
    from agents.bench.common import DEFAULT_CACHE, load_recording
    from agents.bench.tree import synthetic_recordings
    from agents.fleet.fusion import FusionConfig, FusionState, encode_message
    from agents.fleet.fusion.quarantine import QuarantineConfig
    from agents.fleet.robot import robot_map_message
    from mapping.se2 import Pose

    recs = [load_recording(p) for p in synthetic_recordings("museum", n, 0, DEFAULT_CACHE, 0.05)]
    t0 = 1_700_000_000 * 10**9
    boot = t0 - 60 * 10**9
    payloads = [
        [encode_message(robot_map_message(
            rec.robot, rec.start, rec.resolution, rec.frames[(j + k) % len(rec.frames)].wireframe,
            Pose.identity(), j + 1, t0 + j * 10**8, {"boot": boot, "t": 0.1 * j, "step": j}))
         for k, rec in enumerate(recs)]
        for j in range(rounds)
    ]  # fmt: skip
    st = FusionState(FusionConfig(threshold=0.4), quarantine=QuarantineConfig())
    prof = cProfile.Profile()
    digest = hashlib.sha256()
    spent = {"changed": 0.0, "same": 0.0, "dropped": 0.0}
    count = dict.fromkeys(spent, 0)
    fuse_s = 0.0
    for j in range(rounds):
        now = t0 + j * 10**8 + 5 * 10**7
        counting = j >= warm
        for rec, data in zip(recs, payloads[j]):
            accepted = st.stats.accepted
            if profile and counting:
                prof.enable()
            t = time.thread_time()
            taken = st.offer_latest([data], rec.robot, now)
            dt = time.thread_time() - t
            if profile and counting:
                prof.disable()
            what = "changed" if taken.changed else "same" if st.stats.accepted > accepted else "dropped"
            if counting:
                spent[what] += dt
                count[what] += 1
        t = time.thread_time()
        st.fuse(max_realign=0, now=j * 0.1)
        st.realign(now=j * 0.1, limit=1)
        if counting:
            fuse_s += time.thread_time() - t
        digest.update(encode_message(st.fused_message(0)))
    s = st.stats
    digest.update(repr((s.received, s.accepted, s.duplicates, s.outdated, s.absurd, s.quarantined,
                        sorted(s.absurd_by.items()), sorted(s.quarantined_by.items()))).encode())
    maps = sum(count.values())
    if profile:
        pstats.Stats(prof).sort_stats("tottime").print_stats(30)
    return {
        "robots": n, "maps": maps, "ms_per_map": 1000 * sum(spent.values()) / max(maps, 1),
        **{f"ms_{k}": 1000 * spent[k] / max(count[k], 1) for k in spent},
        **{f"n_{k}": count[k] for k in spent},
        "ms_fuse": 1000 * fuse_s / max(rounds - warm, 1), "hash": digest.hexdigest()[:16],
    }


def compare(args: argparse.Namespace) -> None:
    old, new = args.compare.split(",")
    here = os.path.abspath(__file__)
    rows: dict[str, list[dict]] = {old: [], new: []}
    for i in range(args.runs):
        for tree in (old, new) if i % 2 == 0 else (new, old):
            env = dict(os.environ, PYTHONPATH=os.path.abspath(tree))
            load = os.getloadavg()[0]
            out = subprocess.run([sys.executable, here, "--robots", str(args.robots), "--rounds",
                                  str(args.rounds), "--warm", str(args.warm), "--json"],
                                 env=env, cwd="/", capture_output=True, text=True, check=True)
            o = json.loads(out.stdout.strip().splitlines()[-1])
            o["load"] = load
            rows[tree].append(o)
            print(f"{tree}: load {load:.1f}: {line(o)}", flush=True)
    print(f"medians of {args.runs} runs ({args.robots} robots):")
    print("| ms per map (thread time) | " + " | ".join((old, new)) + " |")
    print("| --- | --- | --- |")
    for key in ("ms_per_map", "ms_changed", "ms_same", "ms_dropped", "ms_fuse"):
        print(f"| {key} | " + " | ".join(f"{statistics.median(r[key] for r in rows[t]):.3f}"
                                          for t in (old, new)) + " |")
    print("hashes: " + ", ".join(f"{t}: {sorted({r['hash'] for r in rows[t]})}" for t in (old, new)))


if __name__ == "__main__":
    main()
