"""``wiremap bench register``: global registration of two maps in unrelated frames.

Map pairs
---------
* **Simulated worlds** (built-ins ``paper-small``, ``museum``, ``office``, ``warehouse`` and the
  test worlds ``tests/worlds/*.geojson``). One coverage route per world
  (:func:`agents.sim.route.plan_route`, seeded). A robot's map is the *truth wireframe cropped to
  what an 8 m, 360 degree sensor sees* from poses every ``POSE_STEP`` metres along a stretch of the
  route (:func:`mapping.visibility.visible_view`; where sight of a wall ends the map gets a
  frontier vertex), plus Gaussian noise of ``--noise`` metres on every vertex. This stands in for
  a filter-built map (seconds per pair instead of minutes); it has the filter's partial,
  frontier-ended walls but none of its spurious walls or bent corridors. Each map is expressed in
  its robot's start frame: the start is the stretch's first point with a uniformly random heading,
  so the two frames are unrelated. Stretch lengths and the offset between the two stretches are
  random, from fully overlapping to disjoint.
* **CARMEN logs** (``--data DIR``, default ``../shared/data/carmen`` beside the repository;
  ``--carmen`` pairs): stretches of consecutive scans, read by the project's reader
  (:func:`agents.files.carmen.read_carmen_log`); each scan through split-and-merge
  (:func:`mapping.extract.extract_corners`) and the scans merged at the *true* poses
  (``*.truth.tsv``) with :func:`mapping.merge.merge`.
  Their overlap is measured on the maps themselves (matched wall length at the true transform).
* **Filter-built maps** (``--maps filter``): per world (and per CARMEN log), ``--stretches``
  stretches in overlapping pairs; each robot's map is built by a :class:`mapping.filter.WireframeFilter`
  (the world's paper settings; 6 particles and 0.2 m on a log) fed by
  :func:`agents.mapping_run.simulate` along the stretch (:func:`agents.mapping_run.carmen_inputs`
  on a log), starting at the identity, exactly as a fleet robot. The maps are built once per
  world, seed and count and cached as JSON (``--cache``; building all of them takes tens of
  minutes on a loaded machine, ``--jobs`` builds in parallel); a pair is two of them turned by
  random headings. A filter map drifts, so the transform between the two start poses misplaces
  the far walls: the truth is the *local truth* (:func:`local_truth`, the start-pose truth
  refined on the two maps' walls with a gate from 1.5 m down), and ``false_merges_start_truth``
  counts against the start poses too. Overlap: on the true walls seen from the stretch's true
  poses (simulated), on the maps at the start-pose truth within 0.3 m (logs).
* **Cross pairs**: two maps from two different worlds (or logs). Any acceptance is a false merge.
* **300-corner pairs** (``--large``, default 4; 2 with ``--quick`` unless ``--large`` is given):
  issue 20's speed target, two maps of about 300 corners each. Alternately the whole museum (281
  corners) twice, each copy with its own vertex noise and frame, and what the sensor saw along the
  first and the last 65 % of a museum coverage route (200-270 corners each). Each pair is
  registered three times; its time is the median CPU time (``time.process_time``: one core,
  whatever the other load), and the table's ``300 corners`` line and
  ``ms_per_attempt_300_corners_p50`` give the median over the pairs. They are counted apart from
  the other pairs (``*_300_corners`` keys).

Measures
--------
* *overlap*: the shared wall length over the smaller map's wall length. Simulated: length of the
  truth walls seen in both crops. CARMEN: B's wall length lying on A's walls at the true transform.
* *success*: accepted with a translation error (at B's wall centroid) <= 0.10 m and a rotation
  error <= 1 degree.
* *false merge*: accepted and (a cross pair, or an error above 0.5 m or 2 degrees). Accepted
  within those but outside 0.10 m / 1 degree is counted as *imprecise*.
* time per attempt: :func:`mapping.registration.register` including the per-map preparation.
* *ambiguous by geometry* (simulated pairs of at least 30 % overlap, :func:`truth_ambiguous`):
  the true walls both robots saw recur, noise-free, elsewhere in what one robot saw (the sides
  of a symmetric ring, a featureless hall). No registration can tell the copies apart, so these
  pairs are reported apart: ``success_rate_overlap_ge_30_unambiguous`` leaves them out (and
  ``success_rate_overlap_ge_30`` keeps them); a wrong acceptance of one is still a false merge.

Prints a table by overlap band and, with ``--json``, one JSON object on the last line.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.argtypes import non_negative_int
from agents.errors import UserError
from agents.fleet.carmen_fleet import WRONG_DEG, WRONG_M, error_at

HELP = "global registration of map pairs in unrelated frames"

WORLDS = ("paper-small", "museum", "office", "warehouse")
TEST_WORLDS = Path(__file__).resolve().parents[2] / "tests" / "worlds"
#: The shared real logs beside the repository (``--data`` names another folder).
CARMEN_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "carmen"
MAX_RANGE = 8.0
POSE_STEP = 0.5
BANDS = ((0.0, 0.0), (0.0, 0.1), (0.1, 0.2), (0.2, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 1.01))
SUCCESS_T, SUCCESS_R = 0.10, math.radians(1.0)
FALSE_T, FALSE_R = WRONG_M, math.radians(WRONG_DEG)
FILTER_STRETCHES = 12
FILTER_CACHE_VERSION = 1
#: CARMEN stretches' cache version: 2 since they map through the ``lidar-slam`` profile, 3 since
#: the reader lays a 180- or 360-beam scan from -90 degrees (a reader change is not in the
#: profile's digest: bump this with one).
LOG_CACHE_VERSION = 3
AMBIGUOUS_SUPPORT, AMBIGUOUS_CORNERS = 0.9, 0.9
#: The 300-corner pairs (issue 20's speed target): how many, and the registrations timed per pair.
LARGE_PAIRS, LARGE_REPEATS = 4, 3
LARGE_WORLD = "museum"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pairs", type=int, default=1000, metavar="N",
                        help="same-world pairs (default 1000)")
    parser.add_argument("--cross", type=int, default=None, metavar="N",
                        help="cross-world pairs (default a quarter of --pairs)")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--noise", type=float, default=0.03, metavar="M",
                        help="vertex noise, metres (default 0.03)")
    parser.add_argument("--worlds", default=None, metavar="A,B,...",
                        help="worlds (default the built-ins and tests/worlds/*.geojson)")
    parser.add_argument("--carmen", type=int, default=None, metavar="N",
                        help="CARMEN stretch pairs (default a tenth of --pairs; 0 for none)")
    parser.add_argument("--data", metavar="DIR", default=None,
                        help="CARMEN logs with their truth (*.log.gz, NAME.truth.tsv) for the CARMEN pairs "
                             "(default ../shared/data/carmen beside the repository; skipped when absent)")
    parser.add_argument("--maps", choices=("truth", "filter"), default="truth",
                        help="truth: cropped true walls plus noise (default); filter: maps built by the "
                             "particle filter over route stretches and CARMEN log stretches (cached)")
    parser.add_argument("--stretches", type=int, default=FILTER_STRETCHES, metavar="K",
                        help=f"--maps filter: filter maps per world or log (default {FILTER_STRETCHES})")
    parser.add_argument("--cache", default=None, metavar="DIR",
                        help="--maps filter: cache of the filter maps (default $WIREMAP_CACHE or "
                             "~/.cache/wiremap, subdirectory bench-register)")
    parser.add_argument("--jobs", type=int, default=1, metavar="N",
                        help="--maps filter: processes that build missing filter maps (default 1)")
    parser.add_argument("--large", type=int, default=None, metavar="N",
                        help=f"pairs of ~300-corner museum maps timed apart (default {LARGE_PAIRS}, 2 with "
                             "--quick; 0 for none)")
    parser.add_argument("--quick", action="store_true", help="100 pairs, 30 cross, 10 CARMEN")
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


# ------------------------------------------------------------------------------ simulated maps
@dataclass
class SimWorld:
    name: str
    truth: Any
    route: np.ndarray
    cum: np.ndarray


def _load_worlds(names: list[str], rng: np.random.Generator) -> list[SimWorld]:
    from agents.sim.route import plan_route
    from agents.sim.world import load_world

    out = []
    for name in names:
        world = load_world(name)
        route = plan_route(world, rng, sensor_range=MAX_RANGE)
        seg = np.hypot(*np.diff(route, axis=0).T)
        out.append(SimWorld(world.name, world.truth, route, np.concatenate([[0.0], np.cumsum(seg)])))
    return out


def _poses_along(w: SimWorld, s0: float, s1: float) -> np.ndarray:
    s = np.arange(s0, s1 + 1e-9, POSE_STEP)
    return np.column_stack([np.interp(s, w.cum, w.route[:, 0]), np.interp(s, w.cum, w.route[:, 1])])


def _pose_views(truth: Any, xy: np.ndarray) -> list[list[tuple[int, float, float]]]:
    """Per pose of ``xy``, the truth edges seen from it: ``(edge, t0, t1)``."""
    from mapping.se2 import Pose
    from mapping.visibility import visible_view

    out = []
    for x, y in xy:
        v = visible_view(truth, Pose(float(x), float(y), 0.0), MAX_RANGE)
        out.append([(int(src), float(t0), float(t1))
                    for src, (t0, t1) in zip(v.edge_source.tolist(), v.edge_t.tolist())])
    return out


def _seen_intervals(truth: Any, xy: np.ndarray) -> dict[int, list[tuple[float, float]]]:
    """Per truth edge, the merged parameter intervals seen from the poses ``xy``."""
    return _merged(_pose_views(truth, xy))


def _merged(views: list[list[tuple[int, float, float]]]) -> dict[int, list[tuple[float, float]]]:
    """Per truth edge, the merged parameter intervals of the views (:func:`_pose_views`)."""
    raw: dict[int, list[tuple[float, float]]] = {}
    for view in views:
        for src, t0, t1 in view:
            raw.setdefault(src, []).append((t0, t1))
    out: dict[int, list[tuple[float, float]]] = {}
    for e, iv in raw.items():
        iv.sort()
        merged = [list(iv[0])]
        for a, b in iv[1:]:
            if a <= merged[-1][1] + 1e-6:
                merged[-1][1] = max(merged[-1][1], b)
            else:
                merged.append([a, b])
        out[e] = [(a, b) for a, b in merged]
    return out


def _crop(
    truth: Any, seen: dict[int, list[tuple[float, float]]], noise: float, rng: np.random.Generator
) -> Any:
    """The truth's seen pieces as a wireframe (frontier vertices where a piece ends inside a wall)."""
    from mapping.wireframe import Label, Wireframe

    lengths = truth.edge_lengths()
    pts: list[tuple[float, float]] = []
    labels: list[int] = []
    edges: list[tuple[int, int]] = []
    index: dict[int, int] = {}

    def vertex(v: int) -> int:
        if v not in index:
            index[v] = len(pts)
            pts.append(tuple(truth.points[v]))
            labels.append(int(Label.NOMINAL))
        return index[v]

    def point(p: np.ndarray) -> int:
        pts.append((float(p[0]), float(p[1])))
        labels.append(int(Label.FRONTIER))
        return len(pts) - 1

    for e in sorted(seen):
        i, j = (int(k) for k in truth.edges[e])
        a, b = truth.points[i], truth.points[j]
        for t0, t1 in seen[e]:
            if (t1 - t0) * lengths[e] < 0.1:
                continue
            # Within 2 cm of a corner: the corner itself (the view clips at float precision).
            u = vertex(i) if t0 * lengths[e] <= 0.02 else point(a + t0 * (b - a))
            w = vertex(j) if (1 - t1) * lengths[e] <= 0.02 else point(a + t1 * (b - a))
            edges.append((u, w))
    if not edges:
        return Wireframe.empty()
    p = np.asarray(pts) + rng.normal(0.0, noise, (len(pts), 2))
    return Wireframe.build(p, edges, labels)


def _shared(
    truth: Any, sa: dict[int, list[tuple[float, float]]], sb: dict[int, list[tuple[float, float]]]
) -> float:
    lengths = truth.edge_lengths()
    total = 0.0
    for e in set(sa) & set(sb):
        for a0, a1 in sa[e]:
            for b0, b1 in sb[e]:
                total += max(0.0, min(a1, b1) - max(a0, b0)) * lengths[e]
    return total


def _seen_length(truth: Any, s: dict[int, list[tuple[float, float]]]) -> float:
    lengths = truth.edge_lengths()
    return float(
        sum((b - a) * lengths[e] for e, iv in s.items() for a, b in iv if (b - a) * lengths[e] >= 0.1)
    )


def _stretch(w: SimWorld, rng: np.random.Generator, s0: float | None = None) -> tuple[float, float]:
    total = float(w.cum[-1])
    length = min(0.6 * total, float(rng.uniform(10.0, 50.0)))
    if s0 is None:
        s0 = float(rng.uniform(0.0, max(0.0, total - length)))
    s0 = float(np.clip(s0, 0.0, max(0.0, total - length)))
    return s0, s0 + length


def _start_pose(w: SimWorld, s0: float, rng: np.random.Generator) -> Any:
    from mapping.se2 import Pose

    x = float(np.interp(s0, w.cum, w.route[:, 0]))
    y = float(np.interp(s0, w.cum, w.route[:, 1]))
    return Pose(x, y, float(rng.uniform(-math.pi, math.pi)))


@dataclass
class Sample:
    """One robot's map: in its own frame, with its start pose in the world frame."""

    wf: Any
    start: Any
    seen: dict[int, list[tuple[float, float]]] | None
    length: float
    world: str


def _sim_map(w: SimWorld, s0: float, s1: float, noise: float, rng: np.random.Generator) -> Sample:
    seen = _seen_intervals(w.truth, _poses_along(w, s0, s1))
    crop = _crop(w.truth, seen, noise, rng)
    start = _start_pose(w, s0, rng)
    return Sample(crop.transformed(start.inverse()), start, seen, _seen_length(w.truth, seen), w.name)


def sim_pair(w: SimWorld, rng: np.random.Generator, noise: float) -> tuple[Sample, Sample, float]:
    """Two maps of ``w`` whose stretches are offset at random; returns them and the overlap."""
    a0, a1 = _stretch(w, rng)
    la = a1 - a0
    if rng.random() < 0.2:
        b0, b1 = _stretch(w, rng)  # anywhere: mostly disjoint
    else:
        lb = min(0.6 * float(w.cum[-1]), float(rng.uniform(10.0, 50.0)))
        b0, b1 = _stretch(w, rng, a0 + float(rng.uniform(-lb, la)))
    sa = _sim_map(w, a0, a1, noise, rng)
    sb = _sim_map(w, b0, b1, noise, rng)
    assert sa.seen is not None and sb.seen is not None
    smaller = min(sa.length, sb.length)
    overlap = _shared(w.truth, sa.seen, sb.seen) / smaller if smaller > 0 else 0.0
    return sa, sb, overlap


# ------------------------------------------------------------------------------ 300-corner maps
def large_pairs(n: int, seed: int, noise: float) -> list[tuple[str, Sample, Sample]]:
    """``n`` pairs of large maps of the museum (281 corners in all), alternately *whole* (the
    whole world twice, each copy with its own vertex noise and in its own random frame) and
    *halves* (what the sensor saw along the first and the last 65 % of a coverage route: 200-270
    corners each, 30 % of the route in common)."""
    from mapping.se2 import Pose

    rng = np.random.default_rng([seed, 300])
    w = _load_worlds([LARGE_WORLD], rng)[0]
    total = float(w.cum[-1])
    views = _pose_views(w.truth, _poses_along(w, 0.0, total))
    whole = {e: [(0.0, 1.0)] for e in range(w.truth.n_edges)}
    first = _merged(views[: int(0.65 * len(views))])
    last = _merged(views[int(0.35 * len(views)):])
    out = []
    for k in range(n):
        kind = "whole" if k % 2 == 0 else "halves"
        maps = []
        for seen in ((whole, whole) if kind == "whole" else (first, last)):
            start = Pose(float(rng.uniform(0.0, 200.0)), float(rng.uniform(0.0, 200.0)),
                         float(rng.uniform(-math.pi, math.pi)))
            crop = _crop(w.truth, seen, noise, rng)
            maps.append(Sample(crop.transformed(start.inverse()), start, seen, _seen_length(w.truth, seen),
                               w.name))
        out.append((kind, maps[0], maps[1]))
    return out


def large_rows(pairs: list[tuple[str, Sample, Sample]], repeats: int = LARGE_REPEATS) -> list[dict[str, Any]]:
    """Each pair registered ``repeats`` times: the median CPU time of one process
    (``time.process_time``, preparation included) and the outcome against the truth."""
    from mapping.registration import register

    rows = []
    for kind, sa, sb in pairs:
        times = []
        for _ in range(max(1, repeats)):
            t0 = time.process_time()
            res = register(sa.wf, sb.wf)
            times.append(1e3 * (time.process_time() - t0))
        rows.append({**_judged(res, sa, sb, True, ms=float(np.median(times))), "kind": kind})
    return rows


# ------------------------------------------------------------------------------ CARMEN maps
@dataclass
class Log:
    name: str
    scans: list[Any]  # robot-frame scan wireframes
    poses: list[Any]  # true poses


def _read_log(path: Path, max_range: float = MAX_RANGE) -> Log:
    """The log's laser scans (:func:`agents.files.carmen.read_carmen_log`: its own geometry,
    unreadable lines skipped) through split-and-merge, at their truth poses (the sibling
    ``.truth.tsv`` or the log's ``TRUEPOS``; a log without a truth gives no scans)."""
    from agents.files.carmen import read_carmen_log, scan_truth
    from mapping.extract import extract_corners

    log = read_carmen_log(path)
    poses = scan_truth(log) or []
    scans = []
    for ls in log.scans[: len(poses)]:
        rmax = min(float(ls.max_range), max_range)
        ranges = np.asarray(ls.ranges, dtype=np.float64)
        scans.append(extract_corners(np.where(ranges >= rmax, np.inf, ranges), ls.angles, rmax))
    return Log(path.name.replace(".log.gz", ""), scans, list(poses[: len(scans)]))


def _log_map(log: Log, i0: int, i1: int, rng: np.random.Generator) -> Sample:
    from mapping.merge import MergeConfig, merge
    from mapping.wireframe import Wireframe

    cfg = MergeConfig()
    wf = Wireframe.empty()
    for k in range(i0, i1):
        scan = log.scans[k].transformed(log.poses[k])
        wf = scan if wf.n_edges == 0 else merge(wf, scan, cfg)
    from mapping.se2 import Pose

    p = log.poses[i0]
    start = Pose(p.x, p.y, float(rng.uniform(-math.pi, math.pi)))
    return Sample(wf.transformed(start.inverse()), start, None, wf.total_length(), log.name)


def _true_transform(sa: Sample, sb: Sample) -> Any:
    return sa.start.inverse().compose(sb.start)


def _map_overlap(sa: Sample, sb: Sample, gate: float = 0.2) -> float:
    """Overlap measured on the maps: B's wall length on A's walls at the true transform."""
    from mapping.registration import RegistrationConfig, _match, prepare

    cfg = RegistrationConfig()
    fa, fb = prepare(sa.wf, cfg), prepare(sb.wf, cfg)
    if len(fa.points) == 0 or len(fb.points) == 0:
        return 0.0
    ib, _ = _match(fa, fb, _true_transform(sa, sb), gate, cfg)
    smaller = min(fa.length, fb.length)
    return float(fb.weights[ib].sum()) / smaller if smaller > 0 else 0.0


def log_pair(log: Log, rng: np.random.Generator) -> tuple[Sample, Sample, float]:
    n = len(log.scans)
    la = int(rng.integers(20, 60))
    lb = int(rng.integers(20, 60))
    a0 = int(rng.integers(0, max(1, n - la)))
    b0 = int(np.clip(a0 + int(rng.integers(-lb, la)), 0, max(0, n - lb)))
    sa = _log_map(log, a0, min(n, a0 + la), rng)
    sb = _log_map(log, b0, min(n, b0 + lb), rng)
    return sa, sb, _map_overlap(sa, sb)


# ------------------------------------------------------------------------------ filter-built maps
@dataclass
class FilterMap:
    """One robot's filter-built map over a stretch (its own start frame) and what is true of it."""

    wf: Any
    start: Any  # true pose of the map frame's origin (the stretch's first true pose)
    xy: np.ndarray  # true positions every ~POSE_STEP metres (simulated worlds; empty for logs)
    source: str


def cache_dir(arg: str | None) -> Path:
    base = Path(arg) if arg else Path(os.environ.get("WIREMAP_CACHE", Path.home() / ".cache" / "wiremap"))
    return base / "bench-register"


def _sub_route(w: SimWorld, s0: float, s1: float) -> np.ndarray:
    inner = (w.cum > s0) & (w.cum < s1)
    ends = [np.interp(s, w.cum, w.route[:, k]) for s in (s0, s1) for k in (0, 1)]
    return np.vstack([[ends[0], ends[1]], w.route[inner], [ends[2], ends[3]]])


def _filter_stretches(w: SimWorld, k: int, rng: np.random.Generator) -> list[tuple[float, float]]:
    """``k`` stretches in pairs that overlap like :func:`sim_pair`'s (full to disjoint)."""
    out: list[tuple[float, float]] = []
    while len(out) < k:
        a0, a1 = _stretch(w, rng)
        out.append((a0, a1))
        if len(out) < k:
            lb = min(0.6 * float(w.cum[-1]), float(rng.uniform(10.0, 50.0)))
            out.append(_stretch(w, rng, a0 + float(rng.uniform(-lb, a1 - a0))))
    return out


def _build_world_maps(name: str, seed: int, k: int) -> list[dict[str, Any]]:
    """Filter maps of ``k`` stretches of world ``name``'s route (:func:`agents.mapping_run.simulate`
    along each stretch, a :class:`mapping.filter.WireframeFilter` with the world's paper
    settings starting at the identity), as JSON-ready dicts."""
    from agents import mapping_run as mr
    from agents.sim.world import load_world
    from mapping.filter import WireframeFilter
    from mapping.se2 import Pose

    rng = np.random.default_rng([seed, zlib.crc32(Path(name).stem.encode())])
    w = _load_worlds([name], rng)[0]
    world = load_world(name)
    particles, thr = mr.world_defaults(world)
    cfg = mr.filter_config_for(particles, thr, MAX_RANGE)
    out = []
    for s0, s1 in _filter_stretches(w, k, rng):
        run_seed = int(rng.integers(0, 2**31))
        inputs = list(mr.simulate(world, mr.SimOptions(max_range=MAX_RANGE), run_seed,
                                  route=_sub_route(w, s0, s1)))
        filt = WireframeFilter(cfg, mr.seeds_for(run_seed)["filter"], initial_pose=Pose.identity())
        for inp in inputs:
            filt.step(inp.odometry, inp.scan)
        true = [inp.true_pose for inp in inputs if inp.true_pose is not None]
        every = max(1, round(POSE_STEP / 0.25))
        out.append({"wf": filt.best.to_geojson(), "start": list(true[0].as_tuple()),
                    "xy": [[p.x, p.y] for p in true[::every]], "source": w.name, "stretch": [s0, s1]})
    return out


def _build_log_maps(path: Path, seed: int, k: int) -> list[dict[str, Any]]:
    """Filter maps of ``k`` stretches of a CARMEN log (as ``wiremap run --carmen`` robots map
    them: the ``lidar-slam`` profile)."""
    from agents import mapping_run as mr
    from agents.files.carmen import read_carmen_log, scan_truth
    from mapping.filter import WireframeFilter
    from mapping.se2 import Pose

    log = read_carmen_log(str(path))
    scans = list(log.scans)
    truth = scan_truth(log)
    if truth is None or len(scans) < 40:
        return []
    rng = np.random.default_rng([seed, zlib.crc32(path.name.encode())])
    n = len(scans)
    stretches: list[tuple[int, int]] = []
    while len(stretches) < k:
        la, lb = int(rng.integers(60, 160)), int(rng.integers(60, 160))
        a0 = int(rng.integers(0, max(1, n - la)))
        stretches.append((a0, min(n, a0 + la)))
        if len(stretches) < k:
            b0 = int(np.clip(a0 + int(rng.integers(-lb, la)), 0, max(0, n - lb)))
            stretches.append((b0, min(n, b0 + lb)))
    out = []
    for i0, i1 in stretches:
        part = scans[i0:i1]
        cfg, inputs = mr.profiled_inputs(part, "lidar-slam", 6, 0.2, min(float(part[0].max_range), MAX_RANGE))
        run_seed = int(rng.integers(0, 2**31))
        filt = WireframeFilter(cfg, mr.seeds_for(run_seed)["filter"], initial_pose=Pose.identity())
        for inp in inputs:
            filt.step(inp.odometry, inp.scan)
        out.append({"wf": filt.best.to_geojson(), "start": list(truth[i0].as_tuple()), "xy": [],
                    "source": path.name.replace(".log.gz", ""), "stretch": [i0, i1]})
    return out


def _cached(cache: Path, key: str, build: Any, version: int = FILTER_CACHE_VERSION) -> list[FilterMap]:
    from mapping.se2 import Pose
    from mapping.wireframe import Wireframe

    f = cache / f"{key}-v{version}.json"
    if f.is_file():
        rows = json.loads(f.read_text())
    else:
        rows = build()
        cache.mkdir(parents=True, exist_ok=True)
        tmp = f.with_suffix(".tmp")
        tmp.write_text(json.dumps(rows))
        tmp.replace(f)
    return [FilterMap(Wireframe.from_geojson(r["wf"]), Pose(*r["start"]),
                      np.asarray(r["xy"], dtype=np.float64).reshape(-1, 2), r["source"]) for r in rows]


def _jobs_map(fn: Any, items: list[Any], jobs: int) -> list[Any]:
    if jobs <= 1 or len(items) <= 1:
        return [fn(it) for it in items]
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=jobs) as ex:
        return list(ex.map(fn, items))


def _world_job(item: tuple[str, int, int, str]) -> list[FilterMap]:
    name, seed, k, cache = item
    return _cached(Path(cache), f"{Path(name).stem}-s{seed}-k{k}", lambda: _build_world_maps(name, seed, k))


def _log_job(item: tuple[str, int, int, str]) -> list[FilterMap]:
    path, seed, k, cache = item
    name = Path(path).name.replace(".log.gz", "")
    return _cached(Path(cache), f"carmen-{name}-s{seed}-k{k}-{_profile_digest()}",
                   lambda: _build_log_maps(Path(path), seed, k), LOG_CACHE_VERSION)


def _profile_digest() -> str:
    """8 hex digits of the ``lidar-slam`` profile's configs as they stand (the SLAM's and the
    extractor's defaults included): cached stretch maps are rebuilt when a default changes."""
    from agents import mapping_run as mr

    return hashlib.sha256(repr(mr.split_profile(mr.lidar_profile("lidar-slam"))).encode()).hexdigest()[:8]


def _as_sample(fm: FilterMap, truth: Any, rng: np.random.Generator) -> Sample:
    """``fm`` in a fresh frame (a random turn about its origin), with its seen truth."""
    from mapping.se2 import Pose

    turn = Pose(0.0, 0.0, float(rng.uniform(-math.pi, math.pi)))
    seen = _seen_intervals(truth, fm.xy) if truth is not None and len(fm.xy) else None
    length = _seen_length(truth, seen) if seen is not None else fm.wf.total_length()
    return Sample(fm.wf.transformed(turn.inverse()), fm.start.compose(turn), seen, length, fm.source)


def filter_pair(maps: list[FilterMap], truth: Any, rng: np.random.Generator) -> tuple[Sample, Sample, float]:
    """Two filter maps of one world or log: 80 % a stretch and its partner, else any two."""
    n = len(maps)
    if rng.random() < 0.8:
        i = 2 * int(rng.integers(0, n // 2))
        i, j = (i, i + 1) if rng.random() < 0.5 else (i + 1, i)
    else:
        i = int(rng.integers(0, n))
        j = (i + 1 + int(rng.integers(0, n - 1))) % n
    sa, sb = _as_sample(maps[i], truth, rng), _as_sample(maps[j], truth, rng)
    if sa.seen is not None and sb.seen is not None:
        smaller = min(sa.length, sb.length)
        return sa, sb, _shared(truth, sa.seen, sb.seen) / smaller if smaller > 0 else 0.0
    return sa, sb, _map_overlap(sa, sb, gate=0.3)


# ------------------------------------------------------------------------------ ambiguity of the truth
def _shared_intervals(sa: dict[int, list[tuple[float, float]]],
                      sb: dict[int, list[tuple[float, float]]]) -> dict[int, list[tuple[float, float]]]:
    out: dict[int, list[tuple[float, float]]] = {}
    for e in set(sa) & set(sb):
        iv = [(max(a0, b0), min(a1, b1)) for a0, a1 in sa[e] for b0, b1 in sb[e] if min(a1, b1) > max(a0, b0)]
        if iv:
            out[e] = sorted(iv)
    return out


def truth_ambiguous(
    truth: Any, sa: dict[int, list[tuple[float, float]]], sb: dict[int, list[tuple[float, float]]]
) -> bool:
    """Whether the pair's true transform is not unique by geometry alone.

    The *overlap* (the true walls both robots saw, noise-free, in the world frame) is registered
    onto each robot's seen true walls by the registration's own rotation and vote steps; a
    hypothesis distinct from the identity that matches at least ``AMBIGUOUS_SUPPORT`` of the
    overlap's wall length and ``AMBIGUOUS_CORNERS`` of its real corners, without conflict, means
    that the overlap recurs in what one robot saw (the sides of a symmetric ring, a long featureless
    hall): no registration can tell which copy the other robot saw. Such pairs are reported apart.
    """
    from mapping import registration as rg
    from mapping.se2 import Pose

    cfg = rg.RegistrationConfig()
    quiet = np.random.default_rng(0)
    ov = _crop(truth, _shared_intervals(sa, sb), 0.0, quiet)
    if ov.n_edges == 0:
        return False
    fo = rg.prepare(ov, cfg)
    if len(fo.points) == 0 or len(fo.end_points) == 0:
        return True  # walls without a real corner: nothing fixes the translation along them
    n_corners = len(fo.corner_points)
    for seen in (sa, sb):
        fs = rg.prepare(_crop(truth, seen, 0.0, quiet), cfg)
        for theta in rg.rotation_candidates(fs, fo, cfg).tolist():
            R = rg._rot(theta)
            for t, v in rg._vote(fs, fo, theta, cfg):
                tt = fs.centre + t - R @ fo.centre
                T = rg._refine(fs, fo, Pose(float(tt[0]), float(tt[1]), theta), cfg)
                if not rg._distinct(T, Pose.identity(), fo, cfg):
                    continue
                h = rg._score(fs, fo, T, cfg.match_dist, cfg, v)
                if (h.support >= AMBIGUOUS_SUPPORT * fo.length
                        and rg._matched_corners(fs, fo, T, cfg) >= AMBIGUOUS_CORNERS * n_corners
                        and h.conflict <= cfg.max_conflict + cfg.max_conflict_fraction * h.support):
                    return True
    return False


# ------------------------------------------------------------------------------ scoring
def local_truth(sa: Sample, sb: Sample) -> Any:
    """The true transform of two filter-built maps *at their overlap*
    (:func:`agents.fleet.carmen_fleet.local_truth` from the start poses' truth): a filter-built
    map drifts, and the transform between the two start poses misplaces the other map's far
    walls by the drift of both filters, up to a metre over a CARMEN stretch."""
    from agents.fleet.carmen_fleet import local_truth as at_shared_walls
    from mapping.registration import prepare

    return at_shared_walls(prepare(sa.wf), prepare(sb.wf), _true_transform(sa, sb))


def attempt(sa: Sample, sb: Sample, same: bool, true: Any = None) -> dict[str, Any]:
    """Register B onto A; the row of the result table (``true``: the true transform, default
    the one between the two start poses)."""
    from mapping.registration import register

    t0 = time.perf_counter()
    res = register(sa.wf, sb.wf)
    return _judged(res, sa, sb, same, true, 1e3 * (time.perf_counter() - t0))


def _judged(
    res: Any, sa: Sample, sb: Sample, same: bool, true: Any = None, ms: float = math.nan
) -> dict[str, Any]:
    """The row of the result table for ``res``, the registration of B onto A (``ms``: its time)."""
    row: dict[str, Any] = {
        "accepted": res.accepted, "ms": ms, "confidence": res.confidence, "reason": res.reason,
        "trans_err": math.nan, "rot_err": math.nan, "corners": (sa.wf.n_vertices, sb.wf.n_vertices),
    }
    if res.transform is not None and same:
        start_truth = _true_transform(sa, sb)
        true = start_truth if true is None else true
        c = res.best.transform.inverse().apply(np.zeros((1, 2)))[0] if res.best else np.zeros(2)
        # Error at B's wall centroid (B frame), and in heading.
        from mapping.registration import prepare

        cb = prepare(sb.wf).centre if sb.wf.n_edges else c
        row["trans_err"], row["rot_err"] = error_at(res.transform, true, cb)
        row["trans_err_start"], row["rot_err_start"] = error_at(res.transform, start_truth, cb)
    if res.accepted:
        if not same:
            row["false_merge"] = True
        else:
            row["false_merge"] = row["trans_err"] > FALSE_T or row["rot_err"] > FALSE_R
    else:
        row["false_merge"] = False
    row["success"] = bool(
        res.accepted and same and row["trans_err"] <= SUCCESS_T and row["rot_err"] <= SUCCESS_R
    )
    return row


def _band(ov: float) -> str:
    if ov <= 0.0:
        return "0"
    for lo, hi in BANDS[1:]:
        if lo < ov <= hi or (lo == 0.0 and 0 < ov <= hi):
            return f"{int(lo * 100)}-{min(100, int(hi * 100))}%"
    return "70-100%"


def _pct(v: list[float], q: float) -> float | None:
    a = np.asarray([x for x in v if math.isfinite(x)])
    return None if len(a) == 0 else round(float(np.percentile(a, q)), 4)


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    same = [r for r in rows if r["same"]]
    cross = [r for r in rows if not r["same"]]
    ge30 = [r for r in same if r["overlap"] >= 0.3]
    clear = [r for r in ge30 if not r.get("ambiguous")]
    acc = [r for r in same if r["accepted"] and not r["false_merge"]]
    by: dict[str, dict[str, Any]] = {}
    for label in ["0"] + [f"{int(lo * 100)}-{min(100, int(hi * 100))}%" for lo, hi in BANDS[1:]]:
        rs = [r for r in same if r["band"] == label]
        if not rs:
            continue
        by[label] = {
            "pairs": len(rs),
            "accepted": sum(r["accepted"] for r in rs),
            "success_rate": round(sum(r["success"] for r in rs) / len(rs), 4),
            "false_merges": sum(r["false_merge"] for r in rs),
        }
    return {
        "pairs": len(rows),
        "same_pairs": len(same),
        "cross_pairs": len(cross),
        "carmen_pairs": sum(r["source"] == "carmen" for r in rows),
        "false_merges": sum(r["false_merge"] for r in rows),
        "false_merges_cross": sum(r["false_merge"] for r in cross),
        "false_merges_start_truth": sum(
            bool(
                r["accepted"]
                and r["same"]
                and (r.get("trans_err_start", 0.0) > FALSE_T or r.get("rot_err_start", 0.0) > FALSE_R)
            )
            for r in rows
        ),
        "imprecise_accepts": sum(r["accepted"] and not r["false_merge"] and not r["success"] for r in same),
        "pairs_overlap_ge_30": len(ge30),
        "success_rate_overlap_ge_30": round(sum(r["success"] for r in ge30) / len(ge30), 4) if ge30 else None,
        "pairs_overlap_ge_30_ambiguous": len(ge30) - len(clear),
        "accepted_overlap_ge_30_ambiguous": sum(r["accepted"] for r in ge30 if r.get("ambiguous")),
        "pairs_overlap_ge_30_unambiguous": len(clear),
        "success_rate_overlap_ge_30_unambiguous": round(sum(r["success"] for r in clear) / len(clear), 4)
        if clear
        else None,
        "trans_err_m_p50": _pct([r["trans_err"] for r in acc], 50),
        "trans_err_m_p95": _pct([r["trans_err"] for r in acc], 95),
        "rot_err_deg_p50": _pct([math.degrees(r["rot_err"]) for r in acc], 50),
        "rot_err_deg_p95": _pct([math.degrees(r["rot_err"]) for r in acc], 95),
        "ms_per_attempt_p50": _pct([r["ms"] for r in rows], 50),
        "ms_per_attempt_p95": _pct([r["ms"] for r in rows], 95),
        "by_overlap": by,
        "by_world_overlap_ge_30": {
            name: {"pairs": len(rs), "success_rate": round(sum(r["success"] for r in rs) / len(rs), 4)}
            for name in sorted({r["worlds"][0] for r in ge30})
            for rs in [[r for r in ge30 if r["worlds"][0] == name]]
        },
        "refusal_reasons_overlap_ge_30": _reasons([r for r in ge30 if not r["accepted"]]),
        "by_world_overlap_ge_30_unambiguous": {
            name: {"pairs": len(rs), "success_rate": round(sum(r["success"] for r in rs) / len(rs), 4)}
            for name in sorted({r["worlds"][0] for r in clear})
            for rs in [[r for r in clear if r["worlds"][0] == name]]
        },
        "refusal_reasons_overlap_ge_30_unambiguous": _reasons([r for r in clear if not r["accepted"]]),
    }


def _reasons(rows: list[dict[str, Any]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for r in rows:
        key = r["reason"].split(" (")[0].split(":")[0]
        out[key] = out.get(key, 0) + 1
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def large_summary(large: list[dict[str, Any]]) -> dict[str, Any]:
    """The JSON keys of the 300-corner pairs (None for the rates and times without any)."""
    return {
        "pairs_300_corners": len(large),
        "accepted_300_corners": sum(r["accepted"] for r in large),
        "success_300_corners": sum(r["success"] for r in large),
        "false_merges_300_corners": sum(r["false_merge"] for r in large),
        "ms_per_attempt_300_corners_p50": _pct([r["ms"] for r in large], 50),
        "ms_per_attempt_300_corners_max": _pct([r["ms"] for r in large], 100),
    }


def _print_table(summary: dict[str, Any], rows: list[dict[str, Any]],
                 large: list[dict[str, Any]] | None = None) -> None:
    from agents.bench.common import print_table

    table = [
        [band, v["pairs"], v["accepted"], f"{v['success_rate']:.1%}", v["false_merges"], "-"]
        for band, v in summary["by_overlap"].items()
    ]
    cross = [r for r in rows if not r["same"]]
    table.append(["cross-world", len(cross), sum(r["accepted"] for r in cross), "-",
                  sum(r["false_merge"] for r in cross), "-"])
    if large:
        table.append(["300 corners", len(large), summary["accepted_300_corners"],
                      f"{summary['success_300_corners'] / len(large):.1%}",
                      summary["false_merges_300_corners"],
                      f"{summary['ms_per_attempt_300_corners_p50']:.1f}"])
    print_table(["overlap", "pairs", "accepted", "success", "false merges", "CPU ms p50"], table)
    for src in ("sim", "carmen"):
        rs = [r for r in rows if r["source"] == src and r["same"] and r["overlap"] >= 0.3]
        if rs:
            print(
                f"{src}: overlap >= 30 %: {sum(r['success'] for r in rs)}/{len(rs)} registered "
                "within 0.10 m / 1 deg"
            )


# ------------------------------------------------------------------------------ main
def large_pair_count(args: argparse.Namespace) -> int:
    """``--large`` when given, else 2 with ``--quick``, else :data:`LARGE_PAIRS`."""
    return int(args.large) if args.large is not None else 2 if args.quick else LARGE_PAIRS


def run(args: argparse.Namespace) -> int:
    if args.quick:
        n_pairs, n_cross, n_carmen = 100, 30, 10
    else:
        n_pairs = args.pairs
        n_cross = args.cross if args.cross is not None else max(1, n_pairs // 4)
        n_carmen = args.carmen if args.carmen is not None else n_pairs // 10
    if n_pairs < 0 or n_cross < 0 or n_carmen < 0 or (args.large is not None and args.large < 0):
        raise UserError("pair counts must be >= 0")
    rng = np.random.default_rng(args.seed)
    names = (
        args.worlds.split(",")
        if args.worlds
        else [*WORLDS, *sorted(str(p) for p in TEST_WORLDS.glob("*.geojson"))]
    )
    data = Path(args.data) if args.data else CARMEN_DIR
    if args.data and not data.is_dir():
        raise UserError(f"--data {args.data}: no such directory")
    log_paths = sorted(data.glob("*.log.gz")) if n_carmen else []
    log = (lambda msg: None) if args.quiet else (lambda msg: sys.stderr.write(msg + "\n"))
    if n_carmen and not log_paths:
        log(f"no CARMEN logs in {data}: CARMEN pairs skipped")
    log(f"planning routes in {len(names)} worlds")
    worlds = _load_worlds(names, rng)
    logs: list[Log] = []
    if args.maps == "truth":
        for p in log_paths:
            logs.append(_read_log(p))
            log(f"read {p.name}: {len(logs[-1].scans)} scans")
    fworlds: list[list[FilterMap]] = []
    flogs: list[list[FilterMap]] = []
    if args.maps == "filter":
        k = max(2, 6 if args.quick else int(args.stretches))
        cache = str(cache_dir(args.cache))
        log(f"filter maps: {k} per world and log (cache {cache}; building what is missing)")
        fworlds = _jobs_map(_world_job, [(n, int(args.seed), k, cache) for n in names], int(args.jobs))
        flogs = [m for m in _jobs_map(_log_job, [(str(p), int(args.seed), k, cache) for p in log_paths],
                                      int(args.jobs))
                 if len(m) >= 2]
    rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    have_logs = bool(flogs) if args.maps == "filter" else bool(logs)
    total = n_pairs + n_cross + (n_carmen if have_logs else 0)

    def record(source: str, same: bool, sa: Sample, sb: Sample, overlap: float, truth: Any = None) -> None:
        row = attempt(sa, sb, same, local_truth(sa, sb) if same and args.maps == "filter" else None)
        ambiguous = bool(
            same
            and truth is not None
            and overlap >= 0.3
            and sa.seen is not None
            and sb.seen is not None
            and truth_ambiguous(truth, sa.seen, sb.seen)
        )
        row.update(source=source, same=same, overlap=overlap if same else 0.0,
                   band=_band(overlap) if same else "cross", worlds=(sa.world, sb.world), ambiguous=ambiguous)
        rows.append(row)
        if len(rows) % 25 == 0 or row["false_merge"]:
            fm = sum(r["false_merge"] for r in rows)
            log(
                f"[{len(rows)}/{total}] {time.perf_counter() - t_start:.0f} s, false merges {fm}"
                + (
                    f"  FALSE MERGE {sa.world}/{sb.world} overlap {overlap:.2f} err {row['trans_err']:.2f} m"
                    if row["false_merge"]
                    else ""
                )
            )

    if args.maps == "filter":
        for k_pair in range(n_pairs):
            i = k_pair % len(worlds)
            sa, sb, ov = filter_pair(fworlds[i], worlds[i].truth, rng)
            record("sim", True, sa, sb, ov, worlds[i].truth)
        for k_pair in range(n_carmen if flogs else 0):
            sa, sb, ov = filter_pair(flogs[k_pair % len(flogs)], None, rng)
            record("carmen", True, sa, sb, ov)
        fsources = [(w.truth, m) for w, m in zip(worlds, fworlds)] + [(None, m) for m in flogs]
        for k_pair in range(n_cross):
            i = k_pair % len(fsources)
            j = (i + 1 + int(rng.integers(0, len(fsources) - 1))) % len(fsources)
            pa, pb = (fsources[x][1][int(rng.integers(0, len(fsources[x][1])))] for x in (i, j))
            record("cross", False, _as_sample(pa, None, rng), _as_sample(pb, None, rng), 0.0)
    else:
        for k_pair in range(n_pairs):
            w = worlds[k_pair % len(worlds)]
            sa, sb, ov = sim_pair(w, rng, args.noise)
            record("sim", True, sa, sb, ov, w.truth)
        for k_pair in range(n_carmen if logs else 0):
            lg = logs[k_pair % len(logs)]
            sa, sb, ov = log_pair(lg, rng)
            record("carmen", True, sa, sb, ov)
        sources: list[tuple[str, Any]] = [("sim", w) for w in worlds] + [("carmen", lg) for lg in logs]
        for k_pair in range(n_cross):
            i = k_pair % len(sources)
            j = (i + 1 + int(rng.integers(0, len(sources) - 1))) % len(sources)
            maps = []
            for kind, src in (sources[i], sources[j]):
                if kind == "sim":
                    s0, s1 = _stretch(src, rng)
                    maps.append(_sim_map(src, s0, s1, args.noise, rng))
                else:
                    n = len(src.scans)
                    ln = int(rng.integers(20, 60))
                    i0 = int(rng.integers(0, max(1, n - ln)))
                    maps.append(_log_map(src, i0, min(n, i0 + ln), rng))
            record("cross", False, maps[0], maps[1], 0.0)
    summary = summarise(rows)
    summary["maps"] = args.maps
    n_large = large_pair_count(args)
    large: list[dict[str, Any]] = []
    if n_large > 0:
        log(f"{n_large} pairs of large maps ({LARGE_WORLD})")
        large = large_rows(large_pairs(n_large, int(args.seed), args.noise))
    summary.update(large_summary(large))
    _print_table(summary, rows, large)
    print(f"false merges {summary['false_merges']} (cross {summary['false_merges_cross']}), "
          f"success at >= 30 % overlap {summary['success_rate_overlap_ge_30']} "
          f"(unambiguous {summary['success_rate_overlap_ge_30_unambiguous']} of "
          f"{summary['pairs_overlap_ge_30_unambiguous']}), "
          f"p95 error {summary['trans_err_m_p95']} m / {summary['rot_err_deg_p95']} deg, "
          f"{summary['ms_per_attempt_p50']} ms per attempt (p50)"
          + (f"; 300-corner maps: {summary['ms_per_attempt_300_corners_p50']} ms of CPU per attempt (p50 of "
             f"{summary['pairs_300_corners']} pairs)" if summary["pairs_300_corners"] else ""))
    if args.json:
        print(json.dumps(summary))
    return 0
