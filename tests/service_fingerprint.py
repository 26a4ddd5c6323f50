"""The fusion's intake and fuse as the service runs them, fingerprinted: every fused version and
every verdict over a run of rounds (``python -m tests.service_fingerprint [--robots 16,64]
[--rounds 60]``). Two checkouts print the same lines exactly when they take, refuse and
quarantine the same maps and fuse the same maps after every round (issue 21: the cheaper
quarantine and fuse change neither).

The fleet: ``--robots`` synthetic museum robots (:func:`agents.bench.tree.synthetic_recordings`,
as ``wiremap bench fleet --synthetic`` replays them), robot ``k``'s ``j``-th map its recording's
frame ``(j + k) mod frames`` (they loop, as the bench's replay robots do, so maps grow and
shrink), two robots of three sending each round, stamped 0.1 s apart; plus hostile robots:
``h1`` sends a robot's map, then the same map moved 3 m (its history), ``h2`` junk walls beside
the fleet's walls within 30 m (the fleet's free space), ``h3`` random walls over the building, ``h4`` a
growing map whose new walls wander off. A clock (``now_ns``), the quarantine on, a fast fuse
after each round (``max_realign=1``) and a full one at the end. Prints per fleet size the hash
of every fused map's bytes in turn, the counters and the quarantine's reasons per robot.

To compare two checkouts: ``PYTHONPATH=CHECKOUT python tests/service_fingerprint.py`` in each
(it uses nothing newer than issue 21's start), then ``diff``.
"""

from __future__ import annotations

import argparse
import hashlib

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="16,64")
    ap.add_argument("--rounds", type=int, default=60)
    args = ap.parse_args()
    for n in (int(x) for x in args.robots.split(",")):
        for line in run(n, args.rounds):
            print(line)


def run(n: int, rounds: int) -> list[str]:
    from agents.bench.common import DEFAULT_CACHE, load_recording
    from agents.bench.tree import synthetic_recordings
    from agents.fleet.fusion import FusionConfig, FusionState, encode_message
    from agents.fleet.fusion.quarantine import QuarantineConfig
    from agents.fleet.robot import robot_map_message
    from mapping.se2 import Pose
    from mapping.wireframe import Wireframe

    recs = [load_recording(p) for p in synthetic_recordings("museum", n, 0, DEFAULT_CACHE, 0.05)]
    rng = np.random.default_rng(n)
    t0 = 1_700_000_000 * 10**9
    boot = t0 - 60 * 10**9
    st = FusionState(FusionConfig(threshold=0.4), quarantine=QuarantineConfig())
    digest = hashlib.sha256()
    victim = recs[1 % len(recs)]
    big = max(recs, key=lambda r: r.frames[-1].wireframe.n_edges)

    def put(rid: str, start: Pose, wf: Wireframe, j: int, now: int) -> None:
        msg = robot_map_message(rid, start, 0.05, wf, Pose.identity(), j + 1, t0 + j * 10**8,
                                {"boot": boot, "t": 0.1 * j, "step": j})
        st.offer(encode_message(msg), rid, now)

    for j in range(rounds):
        now = t0 + j * 10**8 + 5 * 10**7
        for k, rec in enumerate(recs):
            if (j + k) % 3 == 0:
                continue
            f = rec.frames[(j + k) % len(rec.frames)]
            put(rec.robot, rec.start, f.wireframe, j, now)
        # h1: a robot's whole map, moved 3 m from its own history after 10 rounds
        wf = big.frames[-1].wireframe
        put("h1", big.start, wf if j < 10 else wf.transformed(Pose(3.0, 2.0, 0.2)), j, now)
        if st.fused.n_edges and j % 4 == 2:  # h2: walls 2.5 m beside the fleet's, parallel to them
            seg = st.fused.segments()
            seg = seg[np.hypot(*(seg[:, 1] - seg[:, 0]).T) > 3.0]
            d = (seg[:, 1] - seg[:, 0]) / np.hypot(*(seg[:, 1] - seg[:, 0]).T)[:, None]
            a = seg.mean(axis=1) + 2.5 * np.stack([-d[:, 1], d[:, 0]], axis=1)
            near = np.hypot(*(a - a[0]).T) < 30.0  # within 30 m of the first
            a, d = a[near], d[near]
            m = len(a)
            pairs = np.stack([np.arange(m), np.arange(m, 2 * m)], 1)
            junk = Wireframe.build(np.concatenate([a, a + 2.0 * d]), pairs)
            start = Pose(*a.mean(axis=0), 0.0)
            put("h2", start, junk.transformed(start.inverse()), j, now)
        if j % 5 == 3:  # h3: random walls over the building, near its own start
            a = rng.uniform(-20.0, 20.0, (30, 2))
            put("h3", victim.start, Wireframe.build(np.concatenate([a, a + rng.normal(0, 2, (30, 2))]),
                                                    np.stack([np.arange(30), np.arange(30, 60)], 1)), j, now)
        # h4: a robot's map, growing by a wall a round that wanders off its walls
        base = victim.frames[-1].wireframe
        w = min(j, 40) + 1
        a = base.points[np.arange(w) % base.n_vertices] + np.array([[1.5 + 0.1 * i, -1.0] for i in range(w)])
        grown = Wireframe.build(np.concatenate([base.points, a, a + 1.0]),
                                np.concatenate([base.edges, np.stack([np.arange(w), np.arange(w, 2 * w)], 1) + base.n_vertices]))  # fmt: skip  # noqa: E501
        put("h4", victim.start, grown, j, now)
        st.fuse(max_realign=1, now=j * 0.1)
        digest.update(encode_message(st.fused_message(0)))
    st.fuse(full=True)
    final = encode_message(st.fused_message(0))
    s = st.stats
    return [
        f"{n} robots, {rounds} rounds: fused maps {digest.hexdigest()[:16]}, "
        f"final {hashlib.sha256(final).hexdigest()[:16]} {len(final)}B v{st.version}",
        f"{n} counters: received {s.received} accepted {s.accepted} duplicates {s.duplicates} "
        f"quarantined {sorted(s.quarantined_by.items())} absurd {sorted(s.absurd_by.items())} "
        f"rejected {sorted(s.rejected_by.items())}",
        f"{n} quarantine: {[(r, q['reason'], q['count']) for r, q in st.quarantine.summary().items()]}",
    ]


if __name__ == "__main__":
    main()
