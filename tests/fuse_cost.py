"""What one fuse of a fleet costs (``python -m tests.fuse_cost [--robots 64] [--rounds 60]
[--profile] [--dump FILE]``): ``--robots`` synthetic museum robots
(:func:`agents.bench.tree.synthetic_recordings`, as ``wiremap bench fleet --synthetic`` replays
them), robot ``k``'s ``j``-th map its recording's frame ``(j + k) mod frames`` (they loop, as
the bench's replay robots do), two robots of three sending each round: at 64 robots about 20
of the 64 leaves change between two fuses (28 of those recordings have one frame only). After
every round a fast fuse (``max_realign=0``, timed: what a map waits for), then one
re-alignment (``realign(limit=1)``, timed apart: the service runs it after the publish); the
first ``--warm`` rounds are not counted (the fleet's first fuses align every robot).

Prints the median and mean thread-time milliseconds per fuse (and the mean per realign), the
merges per fuse (node merges with two non-empty sides), the milliseconds inside the merge
function, and a hash of every fused map in turn (two checkouts fuse alike exactly when the
hashes agree). ``--profile`` adds cProfile's top 30 over the counted fuses; ``--dump FILE``
pickles every merge's inputs ``(round, base, new, threshold)`` of the counted fuses (to time
the merge alone).

A development measurement (figures in ``docs/experiments.md``), not one of ``wiremap bench``'s
benchmarks. To compare two checkouts: ``PYTHONPATH=CHECKOUT python tests/fuse_cost.py``.
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import importlib
import pickle
import pstats
import statistics
import time
from typing import Any


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=60)
    ap.add_argument("--warm", type=int, default=10)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--dump", default=None)
    args = ap.parse_args()

    from agents.bench.common import DEFAULT_CACHE, load_recording
    from agents.bench.tree import synthetic_recordings
    from agents.fleet.fusion import FusionConfig, FusionState, encode_message
    from agents.fleet.robot import robot_map_message
    from mapping.se2 import Pose

    merge_module = importlib.import_module("mapping.merge")  # (``mapping.merge`` is also the function)
    plain_merge = merge_module.merge

    recs = [load_recording(p) for p in synthetic_recordings("museum", args.robots, 0, DEFAULT_CACHE, 0.05)]
    t0 = 1_700_000_000 * 10**9
    inside = [0.0]
    dumped: list[Any] = []
    counting = [False]
    j_now = [0]

    def timed_merge(a: Any, b: Any, config: Any = None, cache: Any = None) -> Any:
        t = time.thread_time()
        out = plain_merge(a, b, config, cache)
        if counting[0]:
            inside[0] += time.thread_time() - t
            if args.dump:
                dumped.append((j_now[0], a, b, config.threshold))
        return out

    merge_module.merge = timed_merge  # the fusion's default merge function calls it (any checkout)
    st = FusionState(FusionConfig(threshold=0.4))
    digest = hashlib.sha256()
    prof = cProfile.Profile()
    per_fuse: list[float] = []
    merges: list[int] = []
    aligning: list[float] = []
    in_merge = 0.0
    for j in range(args.rounds):
        for k, rec in enumerate(recs):
            if (j + k) % 3 == 0:
                continue
            f = rec.frames[(j + k) % len(rec.frames)]
            msg = robot_map_message(rec.robot, rec.start, 0.05, f.wireframe, Pose.identity(), j + 1,
                                    t0 + j * 10**8, {"boot": 1, "t": 0.1 * j, "step": j})
            st.offer(encode_message(msg), rec.robot)
        counting[0] = j >= args.warm
        j_now[0] = j
        m0 = st.merges
        inside[0] = 0.0
        if counting[0] and args.profile:
            prof.enable()
        t = time.thread_time()
        st.fuse(max_realign=0, now=j * 0.1)
        dt = time.thread_time() - t
        if counting[0]:
            per_fuse.append(dt)
            merges.append(st.merges - m0)
            in_merge += inside[0]
        t = time.thread_time()
        st.realign(now=j * 0.1, limit=1)
        if counting[0]:
            aligning.append(time.thread_time() - t)
        if counting[0] and args.profile:
            prof.disable()
        digest.update(encode_message(st.fused_message(0)))
    n = len(per_fuse)
    print(f"{args.robots} robots, {n} fuses: {1000 * statistics.median(per_fuse):.2f} ms per fuse "
          f"(median; mean {1000 * statistics.fmean(per_fuse):.2f}), merges per fuse "
          f"{statistics.median(merges):g} (mean {statistics.fmean(merges):.1f}), "
          f"{1000 * in_merge / n:.2f} ms per fuse inside merge; then a realign "
          f"{1000 * statistics.fmean(aligning):.2f} ms (mean); fused maps {digest.hexdigest()[:16]}"
          + (f"; merge cache hits {st.merge_fn.cache.hits}" if hasattr(st.merge_fn, "cache") else ""))
    if args.profile:
        pstats.Stats(prof).sort_stats("tottime").print_stats(30)
    if args.dump:
        with open(args.dump, "wb") as fh:
            pickle.dump(dumped, fh)


if __name__ == "__main__":
    main()
