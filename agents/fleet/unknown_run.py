"""``wiremap run --unknown-starts`` and ``wiremap run --carmen LOG``: fleets without a shared frame.

* **Unknown starts** (:func:`random_routes`): each robot starts at a random free point of the
  world (seeded by ``--seed``), drives its share of a fleet coverage route from there (then on
  over the others' shares) and publishes its map
  in its own frame with its origin marked unknown. The fused map is in the frame of the fleet's
  root robot (the first registered, or ``--anchor``). ``report.json`` (:func:`write_outputs_unknown`)
  scores it against the truth after one rigid alignment: the root robot's true start pose,
  then :func:`mapping.metrics.align_to_truth`; it lists ``registered`` robots (with the error of
  each registered pose against the true relative start), ``islands``, and every registration
  attempt with its transform's error against the truth, tallied in ``registration_truth``
  (accepted right or wrong, refused right or wrong: a refusal of a right transform is a merge
  lost to caution), and each registered robot's error at its walls (``registration_errors_local``,
  as below).
* **CARMEN fleets** (:mod:`agents.fleet.carmen_fleet`): the log split into overlapping
  stretches, one robot each, in its own odometry frame. ``report.json``
  (:func:`write_outputs_carmen`) scores each robot's map and the fused map by endpoint precision
  (placed by the true first pose of the robot whose frame they are in, no fitting) and each
  registered pose against the truth: at the robot's start (``registration_errors``) and at its
  walls against the local truth where its map meets the others' (``registration_errors_local``;
  a drifting robot's start can be far off while its walls lie right).
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.errors import UserError
from agents.files.io import write_atomic, write_json
from mapping.se2 import Pose
from mapping.wireframe import Wireframe


def random_starts(
    world: Any, n: int, rng: np.random.Generator, clearance: float = 0.4
) -> list[tuple[float, float]]:
    """``n`` random free start points (uniform over the navigable region, at least 2 m apart
    when possible)."""
    import shapely

    from agents.sim.route import navigable_region

    region = navigable_region(world, clearance)
    xmin, ymin, xmax, ymax = region.bounds
    starts: list[tuple[float, float]] = []
    tries = 0
    while len(starts) < n:
        tries += 1
        x, y = float(rng.uniform(xmin, xmax)), float(rng.uniform(ymin, ymax))
        if not region.contains(shapely.Point(x, y)):
            continue
        if tries < 10_000 and any(math.hypot(x - a, y - b) < 2.0 for a, b in starts):
            continue
        starts.append((x, y))
    return starts


def random_routes(
    world: Any, n: int, rng: np.random.Generator, clearance: float = 0.4, spacing: float | None = None
) -> list[Any]:
    """``n`` coverage routes from random free start points (:func:`random_starts`) that share
    the world's coverage out (:func:`agents.sim.route.plan_fleet_routes`): each robot first
    sweeps the part of the world nearest to it that no other robot reaches sooner, then goes on
    over the others' parts."""
    from agents.sim.route import plan_fleet_routes

    return plan_fleet_routes(world, random_starts(world, n, rng, clearance), rng, clearance=clearance,
                             spacing=spacing)


# ---------------------------------------------------------------------- CARMEN
@dataclass
class CarmenWorld:
    """What ``wiremap run`` needs of a log (a CARMEN log or a ROS bag): a name, the scans and
    the truth (or None)."""

    name: str
    path: str
    scans: list[Any]
    truth: list[Pose] | None
    kind: str = "carmen"  # or "rosbag": the report names the input under this key

    @property
    def t0(self) -> float:
        """The log's first stamp: the robots' clock counts from it (some logs stamp in Unix time)."""
        return float(self.scans[0].t)


def carmen_world(args: argparse.Namespace) -> CarmenWorld:
    """The log of ``args.carmen``, or the ROS bag there when ``args.bag`` gives its topics (the
    topics chosen are written back into ``args.bag``); a dense one thinned as its robots thin it
    (:func:`agents.fleet.carmen_fleet.thinned`)."""
    from agents.fleet.carmen_fleet import thinned

    if getattr(args, "bag", None) is not None:
        from agents.files.rosbag import read_rosbag

        bag = read_rosbag(args.carmen, scan_topic=args.bag["scan_topic"], odom_topic=args.bag["odom_topic"],
                          truth_topic=args.bag["truth_topic"])
        if not bag.scans:
            raise UserError(f"{args.carmen}: no scan of {bag.scan_topic} has odometry ({bag.odometry})")
        # the robots read the bag with the topics chosen here (with a truth topic, a bag has two
        # Odometry topics, and a robot would not know which is its odometry)
        args.bag.update(scan_topic=bag.scan_topic, odom_topic=bag.odometry)
        name = Path(str(args.carmen).rstrip("/")).name.split(".")[0]
        return CarmenWorld(name, str(args.carmen), *thinned(list(bag.scans), bag.truth, args.lidar_profile),
                           "rosbag")
    from agents.files.carmen import read_carmen_log, scan_truth

    log = read_carmen_log(args.carmen)
    scans = list(log.scans)
    if not scans:
        raise UserError(f"{args.carmen}: no laser scans in the log")
    truth = scan_truth(log)
    if truth is not None and len(truth) != len(scans):
        truth = truth[: len(scans)] if len(truth) > len(scans) else None
    name = Path(args.carmen).name.split(".")[0]
    return CarmenWorld(name, str(args.carmen), *thinned(scans, truth, args.lidar_profile))


def prepare_carmen(
    out: Path, world: CarmenWorld, ids: list[str], args: argparse.Namespace
) -> list[tuple[int, int]]:
    """The robots' stretches of the log (``routes/<id>.json`` records them)."""
    from agents.fleet.carmen_fleet import split

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {out}: cannot create the directory: {exc.strerror or exc}") from None
    try:
        parts = split(len(world.scans), len(ids), args.overlap)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    for rid, (i0, i1) in zip(ids, parts):
        write_json(out / "routes" / f"{rid}.json", {"log": world.path, "scans": [i0, i1]})
    return parts


# ---------------------------------------------------------------------- reports
def _frames(msg: Any, robots: list[str], state: dict[str, Any]) -> dict[str, Any]:
    """The registration graph's summary from the fused map's meta, with every attempt from the
    store's ``state`` when it has them (the meta carries the last few)."""
    fr = msg.meta.get("frames") if isinstance(msg.meta, dict) else None
    if not isinstance(fr, dict):  # no registration graph: every robot is in the fleet frame
        return {"fleet_root": robots[0] if robots else None, "registered": robots, "islands": {}, "poses": {}}
    every = state.get("registrations")
    if isinstance(every, list) and len(every) >= len(fr.get("registrations", [])):
        fr = {**fr, "registrations": every}
    return fr


def _robot_maps(out: Path, ids: list[str]) -> dict[str, Wireframe]:
    from agents.fleet.fusion import decode_message

    maps = {}
    for rid in ids:
        f = out / "store" / "robots" / f"{rid}.wfm"
        if f.is_file():
            maps[rid] = decode_message(f.read_bytes()).wireframe  # in the robot's own frame
    return maps


def _common(
    out: Path, ids: list[str], duration_s: float, extra: dict[str, Any], raw: bytes, msg: Any,
    state: dict[str, Any],
) -> dict[str, Any]:
    from agents.fleet.fusion import merge_threshold_of

    lat = (state.get("stats") or {}).get("latency_ms") or {}
    write_atomic(out / "fused.wfm", raw)
    statuses = extra.get("robot_status", {})
    return {
        "robots": len(ids),
        "duration_s": round(duration_s, 3),
        "latency_ms": {"p50": lat.get("p50"), "p99": lat.get("p99"), "max": lat.get("max"),
                       "n": lat.get("n", 0)},
        "merge_threshold": merge_threshold_of(msg),
        "map_resolution": float(msg.resolution),
        "fusion": {k: v for k, v in (state.get("stats") or {}).items() if k != "latency_ms"},
        "robot_status": {r: statuses.get(r, {}) for r in ids},
        **{k: v for k, v in extra.items() if k != "robot_status"},
    }


def _registration_report(
    fr: dict[str, Any], starts: dict[str, Pose], maps: dict[str, Wireframe]
) -> dict[str, Any]:
    """The report's registration keys (both kinds of run): the fleet frame's root, who joined
    it, the islands, each registration's error against the true starts and at the registered
    robots' walls (``maps``: each robot's own map), and the attempts."""
    return {
        "fleet_root": fr.get("fleet_root"),
        "registered": list(fr.get("registered", [])),
        "islands": fr.get("islands", {}),
        "registration_errors": _pose_errors(fr, starts),
        "registration_errors_local": _local_errors(fr, starts, maps),
        "registration_attempts": fr.get("attempts", 0),
        **_attempts_against_truth(fr.get("registrations", []), starts),
    }


def _attempts_against_truth(records: list[dict[str, Any]], starts: dict[str, Pose]) -> dict[str, Any]:
    """The attempts (``registrations``), each with its transform's error against the true
    relative start of its two components' roots (``truth_err_m``, ``truth_err_deg``) when both
    are known, and their tally (``registration_truth``): accepted right or wrong (a false merge),
    pending (a first acceptance waiting for its second look: :mod:`agents.fleet.fusion.frames`)
    right or wrong, refused with a right transform (a merge lost to caution) or a wrong one (a
    false merge avoided). A component rooted in the fleet frame has no single true start and is
    left out."""
    from agents.fleet.carmen_fleet import WRONG_DEG, WRONG_M

    out: list[dict[str, Any]] = []
    tally = {"accepted_right": 0, "accepted_wrong": 0, "pending_right": 0, "pending_wrong": 0,
             "refused_right": 0, "refused_wrong": 0}
    for rec in records:
        rec = dict(rec)
        a, b, tf = rec.get("a"), rec.get("b"), rec.get("transform")
        if a in starts and b in starts and tf is not None:
            te, re = _truth_error(tf, starts[a], starts[b])
            rec["truth_err_m"], rec["truth_err_deg"] = te, re
            right = te <= WRONG_M and re <= WRONG_DEG
            what = "accepted" if rec.get("accepted") else "pending" if rec.get("pending") else "refused"
            tally[f"{what}_{'right' if right else 'wrong'}"] += 1
        out.append(rec)
    return {"registrations": out, "registration_truth": tally if starts else {}}


def _pose_errors(fr: dict[str, Any], starts: dict[str, Pose]) -> dict[str, Any]:
    """Each registered robot's pose in the fleet frame against the true relative start."""
    root = fr.get("fleet_root")
    out: dict[str, Any] = {}
    if root not in starts:
        return out
    for rid, p in (fr.get("poses") or {}).items():
        if rid in starts:
            te, re = _truth_error(p, starts[root], starts[rid])
            out[rid] = {"trans_err_m": te, "rot_err_deg": re}
    return out


def _local_errors(fr: dict[str, Any], starts: dict[str, Pose], maps: dict[str, Wireframe]) -> dict[str, Any]:
    """Each registered robot's pose in the fleet frame against the *local truth* where its map
    meets the others' (:func:`agents.fleet.carmen_fleet.local_truth`), at the centre of its
    walls. A robot's own drift turns its map about its start, so a registration that lays its
    walls right on the others' can be half a metre off at its start (``registration_errors``);
    this says how far off its walls are.

    The truth owes nothing to the registrations it scores: from the fleet's root (its frame),
    the robot sharing the most wall with the robots placed so far is placed next, at the true
    relative start refined on their walls (joined, not merged), until every registered robot
    is; a robot sharing no wall with them keeps its true start."""
    from agents.fleet.carmen_fleet import error_at, local_truth, shared_wall
    from mapping.metrics import sample_walls
    from mapping.registration import prepare

    root, poses = fr.get("fleet_root"), fr.get("poses") or {}
    if root not in starts or root not in maps:
        return {}
    placed: dict[str, Pose] = {root: Pose.identity()}
    todo = [r for r in fr.get("registered", []) if r != root and r in maps and r in poses and r in starts]
    feats = {r: prepare(maps[r]) for r in todo}
    out: dict[str, Any] = {}
    while todo:
        parts = [maps[r].transformed(p) for r, p in placed.items()]
        offsets = np.cumsum([0] + [w.n_vertices for w in parts])
        union = Wireframe.build(np.concatenate([w.points for w in parts]),
                                np.concatenate([w.edges + o for w, o in zip(parts, offsets)]))
        fu, samples = prepare(union), sample_walls(union, 0.05)[0]
        best: tuple[float, str, Pose] | None = None
        for rid in todo:
            true = local_truth(fu, feats[rid], starts[root].inverse().compose(starts[rid]))
            shared = shared_wall(samples, maps[rid], true)
            if best is None or shared > best[0]:
                best = (shared, rid, true)
        assert best is not None
        _, rid, true = best
        todo.remove(rid)
        placed[rid] = true
        te, re = error_at(Pose(*poses[rid]), true, feats[rid].centre)
        out[rid] = {"trans_err_m": round(te, 4), "rot_err_deg": round(math.degrees(re), 3)}
    return out


def _truth_error(found: Any, start_a: Pose, start_b: Pose) -> tuple[float, float]:
    """``found`` (x, y, theta: b's frame in a's) against the true ``start_a^-1 start_b``: metres
    (4 decimals) and degrees (3)."""
    from agents.fleet.carmen_fleet import pose_error

    te, re = pose_error(Pose(*found), start_a.inverse().compose(start_b))
    return round(te, 4), round(re, 3)


def write_outputs_unknown(
    out: Path, world: Any, ids: list[str], duration_s: float, extra: dict[str, Any],
    published: bytes | None = None, tracks: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """``report.json`` (and ``fused.*``) of an unknown-starts run (module docstring): the fused
    map is ``published`` when it is the stored version
    (:func:`agents.commands.run.fused_from_store`); ``tracks`` (what
    :func:`agents.commands.run.write_outputs` also takes) are not used: the robots' tracks are
    in their own frames."""
    from agents.commands.run import FLEET_CUT_SHORT, _metrics, fused_from_store, store_state
    from agents.files.render import map_png
    from agents.fleet.fusion import merge_threshold_of
    from agents.fleet.robot import start_pose_of
    from mapping.metrics import align_to_truth

    raw, msg = fused_from_store(out, published)
    wf = msg.wireframe
    robots = list(msg.robots)
    state = store_state(out)
    fr = _frames(msg, robots, state)
    starts: dict[str, Pose] = {}
    for rid in ids:
        try:
            route = np.asarray(json.loads((out / "routes" / f"{rid}.json").read_text())["route"],
                               dtype=np.float64)
            starts[rid] = start_pose_of(route)
        except (OSError, ValueError, KeyError):
            continue
    root = fr.get("fleet_root")
    placed = wf.transformed(starts[root]) if root in starts else wf
    res = float(merge_threshold_of(msg))
    align = align_to_truth(world.truth, placed, 0.1) if placed.n_edges else Pose.identity()
    aligned = placed.transformed(align)
    # As in a run from known starts: a fleet cut short (by --duration or Ctrl-C) before every
    # robot drove its whole route has no cell error worth the name (unexplored area counts).
    statuses = extra.get("robot_status", {})
    covered = all(bool(statuses.get(r, {}).get("finished", False)) for r in ids)
    fused = _metrics(world.truth, aligned, res, partial=not covered, subject=FLEET_CUT_SHORT)
    fused.update({"vertices": wf.n_vertices, "edges": wf.n_edges, "bytes": len(raw), "version": msg.seq,
                  "robots": robots, "alignment": [round(v, 6) for v in align.as_tuple()],
                  "placed_unaligned": _metrics(world.truth, placed, res, partial=not covered,
                                                  subject=FLEET_CUT_SHORT)})
    write_json(out / "fused.geojson",
               aligned.to_geojson({"kind": "fused_map", "world": world.name, "robots": robots,
                                                           "frame": "truth (aligned)"}))
    write_atomic(out / "fused.png", map_png(aligned, world.truth))
    per_robot: dict[str, Any] = {}
    maps = _robot_maps(out, ids)
    for rid, rwf in maps.items():
        m = _metrics(world.truth, rwf.transformed(starts[rid]), res, partial=True) if rid in starts else {}
        m.update({"vertices": rwf.n_vertices, "edges": rwf.n_edges})
        per_robot[rid] = m
    report = {
        "world": world.name,
        "unknown_starts": True,
        **_registration_report(fr, starts, maps),
        "fused": fused,
        "per_robot": per_robot,
        "resolution": res,
    }
    report.update(_common(out, ids, duration_s, extra, raw, msg, state))
    _robot_progress(report, ids)
    write_json(out / "report.json", report)
    return _summary_shape(report, ids)


def write_outputs_carmen(
    out: Path, world: Any, ids: list[str], duration_s: float, extra: dict[str, Any],
    published: bytes | None = None, tracks: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """``report.json`` (and ``fused.*``) of a CARMEN fleet run (module docstring); ``published``
    and ``tracks`` as :func:`write_outputs_unknown`."""
    from agents.commands.run import fused_from_store, store_state
    from agents.fleet.carmen_fleet import endpoint_precision, endpoints
    from mapping.lidar_metrics import align_to_points

    raw, msg = fused_from_store(out, published)
    wf = msg.wireframe
    robots = list(msg.robots)
    state = store_state(out)
    fr = _frames(msg, robots, state)
    stretches: dict[str, tuple[int, int]] = {}
    for rid in ids:
        try:
            i0, i1 = json.loads((out / "routes" / f"{rid}.json").read_text())["scans"]
            stretches[rid] = (int(i0), int(i1))
        except (OSError, ValueError, KeyError):
            continue
    truth = world.truth
    starts = {r: truth[i0] for r, (i0, _) in stretches.items()} if truth is not None else {}
    root = fr.get("fleet_root")
    fused: dict[str, Any] = {"vertices": wf.n_vertices, "edges": wf.n_edges, "bytes": len(raw),
                             "version": msg.seq, "robots": robots}
    per_robot: dict[str, Any] = {}
    maps = _robot_maps(out, ids)
    if truth is not None:
        ends = endpoints(world.scans, truth)
        placed = wf.transformed(starts[root]) if root in starts else wf
        fused["endpoint_precision"] = round(endpoint_precision(placed, ends), 4)
        # the fleet frame is the root robot's odometry frame, placed at its true start; its own
        # drift turns the whole map about that start. Scored also after one rigid alignment to
        # the endpoints, as an unknown-starts simulation is scored against the true walls.
        align = align_to_points(placed, ends)
        fused["endpoint_precision_aligned"] = round(endpoint_precision(placed.transformed(align), ends), 4)
        fused["alignment"] = [round(v, 6) for v in align.as_tuple()]
        write_atomic(out / "fused.png", _carmen_figure(world.name, placed, ends, truth, stretches, fr, root,
                                                       fused["endpoint_precision"]))
        write_json(out / "fused.geojson",
                   placed.to_geojson({"kind": "fused_map", "log": world.name, "robots": robots,
                                                              "frame": "truth"}))
        for rid, rwf in maps.items():
            i0, i1 = stretches[rid]
            own = endpoints(world.scans[i0:i1], truth[i0:i1])
            per_robot[rid] = {
                "scans": [i0, i1], "vertices": rwf.n_vertices, "edges": rwf.n_edges,
                "endpoint_precision": round(endpoint_precision(rwf.transformed(starts[rid]), ends), 4),
                "endpoint_precision_own_scans": round(endpoint_precision(rwf.transformed(starts[rid]), own),
                                                      4),
            }
    report = {
        "log": world.name,
        world.kind: world.path,
        **_registration_report(fr, starts, maps),
        "fused": fused,
        "per_robot": per_robot,
    }
    report.update(_common(out, ids, duration_s, extra, raw, msg, state))
    _robot_progress(report, ids, t0=world.t0)
    write_json(out / "report.json", report)
    return _summary_shape(report, ids)


def _carmen_figure(
    log: str, placed: Wireframe, ends: Any, truth: list[Pose], stretches: dict[str, tuple[int, int]],
    fr: dict[str, Any], root: Any, precision: float,
) -> bytes:
    """The fused map of a CARMEN fleet run in the truth frame, over the log's real scan endpoints
    (at the truth poses), with each robot's true path over its stretch in its colour (a robot
    left as an island is marked so: its walls are not in this map)."""
    from agents.files.render import map_figure

    in_map = {str(root), *map(str, fr.get("registered", []))}
    paths = {
        (rid if rid in in_map else f"{rid} (island, not in this map)"):
            np.array([[p.x, p.y] for p in truth[i0:i1]], dtype=np.float64)
        for rid, (i0, i1) in sorted(stretches.items())
    }
    islands = [m for m in (fr.get("islands") or {}).values()]
    fused = "+".join(sorted(in_map & set(stretches))) or "none"
    alone = f", island {' '.join('+'.join(map(str, m)) for m in islands)}" if islands else ""
    title = f"{log}: fused {fused}{alone}, precision {precision:.2f}"
    return map_figure(placed, None, title=title, trajectories=paths, points=ends,
                      points_label="real scan endpoints (truth poses)")


def _robot_progress(report: dict[str, Any], ids: list[str], t0: float = 0.0) -> None:
    """Each robot's figures from its last status into ``per_robot``, as a run from known starts
    reports them (:func:`agents.commands.run.status_figures`); ``sim_time_s`` counted from
    ``t0`` (:attr:`CarmenWorld.t0`)."""
    from agents.commands.run import status_figures

    for rid in ids:
        r = report["per_robot"].setdefault(rid, {})
        for k, v in status_figures(report.get("robot_status", {}).get(rid, {}), t0).items():
            r.setdefault(k, v)


def _summary_shape(report: dict[str, Any], ids: list[str]) -> dict[str, Any]:
    """The keys ``run._print_summary`` reads, filled where a run of this kind has none."""
    f = report["fused"]
    for k in ("wall_recall", "wall_precision"):
        f.setdefault(k, f.get("endpoint_precision", float("nan")) if k == "wall_precision" else float("nan"))
    f.setdefault("cell_error", None)
    for rid in ids:
        r = report["per_robot"].setdefault(rid, {})
        r.setdefault("wall_recall", float("nan"))
        r.setdefault("wall_precision", r.get("endpoint_precision", float("nan")))
    return report
