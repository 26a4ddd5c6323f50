"""What one robot map costs the fusion's intake (``python -m tests.offer_cost [--robots 64]
[--frames 40] [--service] [--profile]``): the maps of ``--robots`` synthetic museum robots
(:func:`agents.bench.tree.synthetic_recordings`, as ``wiremap bench fleet --synthetic`` replays
them; generated into ``out/bench-cache`` when absent), ``--frames`` maps each (robot ``k``'s
``j``-th map is its recording's ``j``-th frame, stamped 0.1 s apart), each given to
:meth:`FusionState.offer`; prints the milliseconds per offer.

Without ``--service`` a bare ``FusionState()`` (no clock, no quarantine: the codec, the content
checks, the budgets and the bookkeeping; issue 21's micro-benchmark). With ``--service`` as the
fusion service runs it: a clock (``now_ns``), the quarantine's consistency checks on, each
round of maps followed by a fast fuse (so the fleet's map grows and every robot is judged
against it). ``--profile`` adds cProfile's top 25 (and its overhead: about twice the time).

A development measurement (figures in ``docs/experiments.md``), not one of ``wiremap bench``'s
benchmarks. To compare two checkouts, run this file in each (``PYTHONPATH=CHECKOUT python
tests/offer_cost.py``; it uses nothing newer than issue 21's start).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, default=64)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--service", action="store_true", help="clock, quarantine, a fuse per round")
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args()

    from agents.bench.common import DEFAULT_CACHE, load_recording
    from agents.bench.tree import synthetic_recordings
    from agents.fleet.fusion import FusionConfig, FusionState, encode_message
    from agents.fleet.fusion.quarantine import QuarantineConfig
    from agents.fleet.robot import robot_map_message

    recs = [load_recording(p) for p in synthetic_recordings("museum", args.robots, 0, DEFAULT_CACHE, 0.05)]
    t0 = time.time_ns() - 60 * 10**9
    boot = t0 - 10**9
    rounds = []
    for j in range(args.frames):
        rounds.append([
            (rec.robot, encode_message(robot_map_message(
                rec.robot, rec.start, rec.resolution, rec.frames[min(j, len(rec.frames) - 1)].wireframe,
                rec.frames[min(j, len(rec.frames) - 1)].pose, j + 1, t0 + j * 10**8,
                {"boot": boot if args.service else 1, "t": 0.1 * j, "step": j})))
            for rec in recs
        ])  # fmt: skip
    if args.service:
        st = FusionState(FusionConfig(threshold=0.4), quarantine=QuarantineConfig())
    else:
        st = FusionState()
    prof = cProfile.Profile()
    spent = 0.0
    n = 0
    for j, batch in enumerate(rounds):
        now = t0 + j * 10**8 + 5 * 10**7 if args.service else None
        t = time.perf_counter()
        if args.profile:
            prof.enable()
        for rid, data in batch:
            st.offer(data, rid, now)
        if args.profile:
            prof.disable()
        spent += time.perf_counter() - t
        n += len(batch)
        if args.service:
            st.fuse(max_realign=0)
    s = st.stats
    print(f"{1000 * spent / n:.3f} ms per offer over {n} maps of {len(recs)} robots "
          f"({'service' if args.service else 'bare state'}{', profiled' if args.profile else ''}); "
          f"accepted {s.accepted}, absurd {s.absurd}, quarantined {s.quarantined}")
    if args.profile:
        pstats.Stats(prof).sort_stats("cumulative").print_stats(25)


if __name__ == "__main__":
    main()
