"""The fusion tree in ``wiremap bench fleet --fusers K``: start ``K`` regional fusers and a root
instead of one fusion service, and measure each level.

* ``latency_ms_p50/p99`` (end to end, as for one fuser): robot publish -> the root's fused
  publish that includes the map (the stamps each partial carries), from the root's
  ``latency.log``;
* ``regional_ms_p50/p99``: robot publish -> its regional fuser's partial publish (their
  stores' ``latency.log``); ``root_ms_p50/p99``: partial publish -> fused publish (the root's
  ``fused/stats``);
* ``fuser_cpu``: each fuser process's CPU seconds over the window's wall seconds;
  ``fusion_cpu_share`` their sum;
* ``link_bytes_per_s``: payload bytes per second on each hop, counted by a subscriber on the
  router: ``robots->regional`` (robot maps), ``regional->root`` (partials), ``root->clients``
  (fused maps). On one router these hops are its links to those processes; across sites
  (broker_config/README.md) the first stays inside a site and only the partials cross.

``--synthetic`` replaces the recorded filter runs by synthetic robots (:func:`synthetic_recordings`:
views of the world's true walls that grow as the robot explores, with noise), cheap to make
for 64 robots; what the fleet benchmark measures at those sizes is transport and fusion.
"""

from __future__ import annotations

import itertools
import os
import threading
from pathlib import Path
from typing import Any

import numpy as np

from agents.fleet.fusion.tree import fold_ranges


def synthetic_recordings(world_spec: str, n: int, seed: int, cache: str | os.PathLike[str],
                         resolution: float, frames: int = 150, radius: float = 6.0) -> list[Path]:
    """Recordings (:func:`agents.bench.common.save_recording`) of ``n`` synthetic robots
    ``r1..rn``: robot ``k`` walks a straight line from near a random corner of the world at 0.3 m per
    frame and its map is every true wall with both ends within ``radius`` (6 m) of a point it has passed,
    each vertex with its own fixed noise (0.03 m), in its odometry frame; only frames whose map
    changed are kept."""
    from agents.bench.common import Frame, Recording, save_recording
    from agents.sim.world import load_world
    from mapping.se2 import Pose
    from mapping.wireframe import Label, Wireframe

    world = load_world(world_spec)
    d = Path(cache) / f"synthetic-{world.name}-n{n}-s{seed}-r{resolution:g}-f{frames}-R{radius:g}"
    paths = [d / f"r{k + 1}.wrp" for k in range(n)]
    if all(p.is_file() for p in paths):
        return paths
    truth = world.truth
    lo, hi = truth.points.min(axis=0), truth.points.max(axis=0)
    for k, path in enumerate(paths):
        rng = np.random.default_rng(seed * 1000 + k)
        v0 = int(truth.edges[int(rng.integers(truth.n_edges)), 0])
        c0 = truth.points[v0] + rng.uniform(-2.0, 2.0, 2)  # by a wall
        ang = rng.uniform(-np.pi, np.pi)
        step = 0.3 * np.array([np.cos(ang), np.sin(ang)])
        noise = rng.normal(0.0, 0.03, truth.points.shape)
        origin = Pose(float(c0[0]), float(c0[1]), float(rng.uniform(-np.pi, np.pi)))
        seen = np.zeros(truth.n_vertices, dtype=bool)
        at = (truth.edges[:, 0] == v0) | (truth.edges[:, 1] == v0)
        seen[truth.edges[at].ravel()] = True  # the first wall, however long
        out: list[Frame] = []
        last = -1
        for i in range(frames):
            c = np.clip(c0 + i * step, lo, hi)
            seen |= np.linalg.norm(truth.points - c, axis=1) <= radius
            keep = seen[truth.edges[:, 0]] & seen[truth.edges[:, 1]]
            count = int(keep.sum())
            if count == last or count == 0:
                continue
            last = count
            edges = truth.edges[keep]
            used = np.unique(edges)
            remap = -np.ones(truth.n_vertices, dtype=np.int64)
            remap[used] = np.arange(len(used))
            labels = truth.labels[used].copy()
            deg = np.bincount(remap[edges].ravel(), minlength=len(used))
            labels[deg == 1] = Label.FRONTIER
            wf = Wireframe(truth.points[used] + noise[used], labels, remap[edges].astype(np.int32),
                           np.full(len(edges), 0.6), np.zeros(len(edges), dtype=np.uint64))
            pose = origin.inverse().compose(Pose(float(c[0]), float(c[1]), origin.theta))
            out.append(Frame(0.1 * i, pose, None, wf.transformed(origin.inverse())))
        rec = Recording(f"r{k + 1}", world.name, origin, resolution, tuple(out), frames, None)
        save_recording(path, rec)
    return paths


def start_tree(
    procs: Any, k: int, ids: list[str], bus: list[str], d: Path, thr: float, interval: float = 0.0
) -> list[str]:
    """Start ``k`` regional fusers over the fold's subtrees of ``ids`` (each fusing at most every
    ``interval`` seconds) and the root; returns the fuser process names (``g0..``, ``root``)
    once all are ready."""
    names = []
    for g, pattern in enumerate(fold_ranges(ids, k)):  # id ranges, as wiremap run --fusers gives
        name = f"g{g}"
        procs.start(name, ["-m", "agents", "fuse", *bus, "--group", name, "--robots", pattern,
                           "--store", str(d / f"store-{name}"), "--threshold", repr(thr),
                           "--min-interval", repr(interval)])
        names.append(name)
    procs.start("root", ["-m", "agents", "fuse", *bus, "--of-groups", ",".join(names),
                         "--store", str(d / "store"), "--threshold", repr(thr),
                         "--min-interval", repr(interval)])
    for name in names:
        procs.wait_log(name, "ready", 90.0)
    procs.wait_log("root", "root fuser ready", 90.0)
    return [*names, "root"]


class LinkCounter:
    """Payload bytes per hop of the tree, counted by subscribers on the router (see the module
    docstring)."""

    def __init__(self, session: Any, prefix: str) -> None:
        self.lock = threading.Lock()
        self.bytes = {"robots->regional": 0, "regional->root": 0, "root->clients": 0}
        self.on = False
        self.prefix = prefix
        self.partial_times: dict[str, list[float]] = {}  # group -> arrival times (monotonic)
        self.subs = [
            session.declare_subscriber(f"{prefix}/robots/*/map", lambda s: self._add("robots->regional", s)),
            session.declare_subscriber(f"{prefix}/groups/*/map", lambda s: self._add("regional->root", s)),
            session.declare_subscriber(f"{prefix}/fused/map", lambda s: self._add("root->clients", s)),
        ]

    def _add(self, hop: str, sample: Any) -> None:
        if hop == "regional->root":
            import time

            g = str(sample.key_expr).split("/")[-2]
            with self.lock:
                self.partial_times.setdefault(g, []).append(time.monotonic())
        if self.on:
            n = len(sample.payload)
            with self.lock:
                self.bytes[hop] += n

    def max_gap(self, group: str, t0: float, t1: float) -> float | None:
        """The longest time (s) without a partial of ``group`` over ``[t0, t1]``."""
        with self.lock:
            ts = [t for t in self.partial_times.get(group, []) if t0 <= t <= t1]
        if not ts:
            return None
        ts = [t0, *ts, t1]
        return max(b - a for a, b in itertools.pairwise(ts))

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


def level_latencies(d: Path, names: list[str], w0: int, w1: int) -> dict[str, list[float]]:
    """The regional fusers' latency samples (robot publish -> partial publish) in the window."""
    from agents.fleet.fusion import LATENCY_LOG

    out: list[float] = []
    for name in names:
        if name == "root":
            continue
        try:
            text = (d / f"store-{name}" / LATENCY_LOG).read_text()
        except OSError:
            continue
        for line in text.splitlines():
            parts = line.split()
            if len(parts) == 3:
                try:
                    ms, t = float(parts[1]), int(parts[2])
                except ValueError:
                    continue
                if w0 <= t <= w1:
                    out.append(ms)
    return {"regional": out}
