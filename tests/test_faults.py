"""Faults over real processes on loopback: a robot, the fusion service or the router killed with
SIGKILL and restarted. Each test prints the figure it measures (``FIGURE name = value`` lines,
also junit properties).

Every process is started through :class:`tests.fleet_util.Fleet` (stopped and reaped in a
``finally``), every session is closed by a context manager, and every wait is on an event or a
condition with a deadline.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from agents.fleet.bus import FleetKeys
from agents.fleet.fusion import decode_message, read_store
from tests.fleet_util import (
    Fleet,
    FusedWatcher,
    client,
    free_port,
    in_process_router,
    query_fused,
    query_stats,
    record,
    tcp_endpoint,
    wait_until,
)

pytestmark = pytest.mark.fleet

WORLD = "paper-small"
# Short routes in two different rooms of paper-small (see `wiremap world show paper-small`)
SHORT = {"r1": "2,2;5,2", "r2": "10,9;13,9"}
# Longer loops, so that the robots are still mapping while something else fails
LOOP = {"r1": "1.5,1.5;5.5,1.5;5.5,5.5;1.5,5.5;1.5,1.5", "r2": "10,9;13.5,9;13.5,13.5;10,13.5;10,9"}


def robot_args(
    rid: str, ep: str, fleet: str, route: str, tmp: Path, *, rate: float, heartbeat: float = 0.5
) -> list[Any]:
    return [
        "robot", "--id", rid, "--world", WORLD, "--route", route, "--rate", rate, "--particles", "3",
        "--heartbeat", heartbeat, "--viz-rate", "1", "--seed", "7", "--connect", ep, "--fleet", fleet,
        "--status-file", tmp / f"{rid}.status.json",
    ]  # fmt: skip


class MapTap:
    """The latest ``(boot, seq)`` and map each robot published, and its latest pose status, as
    seen by the test's own subscribers."""

    def __init__(self, session: zenoh.Session, keys: FleetKeys) -> None:
        self.latest: dict[str, tuple[int, int]] = {}
        self.maps: dict[str, Any] = {}
        self.status: dict[str, dict[str, Any]] = {}
        self.lock = threading.Lock()
        self.keys = keys
        self.sub = session.declare_subscriber(keys.all_maps, self._cb)
        self.sub_pose = session.declare_subscriber(keys.all_poses, self._on_pose)

    def _on_pose(self, sample: zenoh.Sample) -> None:
        from agents.fleet.bus import decode_pose

        rid = self.keys.robot_of(str(sample.key_expr))
        p = decode_pose(sample.payload.to_bytes())
        with self.lock:
            if rid is not None:
                self.status[rid] = p["status"]

    def finished(self, *rids: str) -> bool:
        with self.lock:
            return all(self.status.get(r, {}).get("finished", False) for r in rids)

    def _cb(self, sample: zenoh.Sample) -> None:
        m = decode_message(sample.payload.to_bytes())
        k = (int(m.meta.get("boot", 0)), int(m.seq))
        with self.lock:
            if k > self.latest.get(m.sender, (-1, -1)):
                self.latest[m.sender] = k
                self.maps[m.sender] = m

    def snapshot(self) -> dict[str, tuple[int, int]]:
        with self.lock:
            return dict(self.latest)

    def close(self) -> None:
        self.sub.undeclare()
        self.sub_pose.undeclare()


def stats_robot_keys(doc: dict[str, Any] | None) -> dict[str, tuple[int, int]]:
    if not doc:
        return {}
    return {r: (int(v["boot"]), int(v["seq"])) for r, v in doc["robots"].items()}


def bit_of(m: Any, rid: str) -> int:
    return 1 << list(m.robots).index(rid)


# ---------------------------------------------------------------------- a robot dies
def test_robot_kill9_marks_stale_keeps_its_walls_and_a_restart_replaces_them(tmp_path: Path, record_property):
    """kill -9 of robot r1: the fusion service sees its token go within a second and flags it
    stale (fused map metadata and the Rerun recording) without touching the walls; r1
    restarted with the same id (a new boot) replaces its stale map and is no longer stale."""
    from agents.files.rerun_log import read_recording

    keys = FleetKeys("k9")
    rrd = tmp_path / "fuse.rrd"
    with in_process_router() as ep, Fleet(tmp_path) as fleet, client(ep) as s:
        w = FusedWatcher(s, keys)
        tap = MapTap(s, keys)
        try:
            fleet.start("fuse", ["fuse", "--connect", ep, "--fleet", keys.fleet, "--rrd", rrd])
            fleet.wait_log("fuse", "fusion service ready", 30)
            for rid in ("r1", "r2"):
                fleet.start(rid, robot_args(rid, ep, keys.fleet, SHORT[rid], tmp_path, rate=20))
            # both routes done (a map of every step is out), fused with both robots
            wait_until(lambda: tap.finished("r1", "r2"), 60, "both robots at the end of their routes")
            w.wait_for(lambda m: m.robots == ("r1", "r2") and not m.meta.get("stale"), 30, "r1 and r2")
            wait_until(lambda: (d := query_stats(s, keys))
                       and stats_robot_keys(d).get("r1") == tap.snapshot().get("r1"),
                       10, "the fusion service has r1's latest map")  # fmt: skip
            before = query_fused(s, keys)
            r1_map = tap.maps["r1"]
            n0 = w.count()
            t_kill = fleet.kill9("r1")
            stale, t_stale = w.wait_for_timed(lambda m: "r1" in m.meta.get("stale", []), 10,
                                              "r1 stale", since=n0)
            detect_s = t_stale - t_kill
            record(record_property, "robot_token_loss_detection_s", round(detect_s, 3))
            assert detect_s < 1.0
            # the walls are untouched: same version, same map; r1 still owns its walls
            assert stale.seq == before.seq and stale.robots == ("r1", "r2")
            assert stale.wireframe.almost_equal(before.wireframe, tol=1e-9, likelihood_tol=1e-9)
            mine = (stale.wireframe.sources & np.uint64(bit_of(stale, "r1"))) != 0
            assert mine.sum() >= 2
            # every wall r1 reported (fleet frame) lies along a fused wall of r1
            segs = r1_map.wireframe.transformed(r1_map.origin).segments()
            fused_mine = stale.wireframe.segments()[mine]
            for mid in segs.mean(axis=1):
                assert _distance_to_segments(mid, fused_mine) < 0.3
            # the queryable answers the stale map too
            q = query_fused(s, keys)
            assert q is not None and "r1" in q.meta["stale"] and q.seq == stale.seq
            old_boot = stats_robot_keys(query_stats(s, keys))["r1"][0]
            # r1 comes back with the same id: a new boot supersedes the stale map
            n1 = w.count()
            t_restart = time.monotonic()
            fleet.start("r1b", robot_args("r1", ep, keys.fleet, SHORT["r1"], tmp_path, rate=20))
            _, t_back = w.wait_for_timed(
                lambda m: "r1" in m.robots and "r1" not in m.meta.get("stale", []), 60, "r1 back", since=n1
            )
            wait_until(lambda: stats_robot_keys(query_stats(s, keys)).get("r1", (0, 0))[0] > old_boot, 30,
                       "r1's new boot in the fusion service")  # fmt: skip
            record(record_property, "robot_restart_to_not_stale_s", round(t_back - t_restart, 3))
            doc = query_stats(s, keys)
            assert doc is not None and doc["stale"] == [] and sorted(doc["alive"]) == ["r1", "r2"]
        finally:
            tap.close()
            w.close()
        assert fleet.stop("fuse", signal.SIGTERM, timeout=20) == 0, fleet.log("fuse")
    log = (tmp_path / "fuse.log").read_text()
    assert "stale robots: r1" in log and "robots back: r1" in log and "Traceback" not in log
    entities, _ = read_recording(rrd)
    assert {"/robots/r1/status", "/stats/robots/r1/alive", "/robots/r1/map"} <= entities
    texts = _recording_texts(rrd, "/robots/r1/status")
    assert any("stale" in t for t in texts) and any("alive again" in t for t in texts), texts


def _distance_to_segments(p: np.ndarray, segs: np.ndarray) -> float:
    a, b = segs[:, 0], segs[:, 1]
    d = b - a
    L2 = np.maximum((d * d).sum(axis=1), 1e-18)
    t = np.clip(((p - a) * d).sum(axis=1) / L2, 0.0, 1.0)
    q = a + t[:, None] * d
    return float(np.hypot(*(q - p).T).min())


def _recording_texts(path: Path, entity: str) -> list[str]:
    from rerun.chunk import RrdReader

    out: list[str] = []
    for c in RrdReader(str(path)).stream().to_chunks():
        if str(c.entity_path) != entity:
            continue
        batch = c.to_record_batch()
        for name in batch.schema.names:
            if name.endswith("TextLog:text"):
                for v in batch.column(name).to_pylist():
                    out.extend(str(x) for x in (v if isinstance(v, list) else [v]))
    return out


# ---------------------------------------------------------------------- the fusion service dies
def test_fusion_kill9_restarts_from_its_store_with_the_same_map(tmp_path: Path, record_property):
    """kill -9 of the fusion service while two robots map: restarted on the same store, its
    first fused map (published before it takes any robot message) is the last stored one --
    the same version and walls, and a map the old service had published -- and it then catches
    up with each robot's latest map.

    The store is written at most once a second (``--save-interval``, one atomic snapshot), so
    the comparison is with the last *stored* fused map; what came after is restored by the
    robots' next maps (each re-sends at least every heartbeat)."""
    keys = FleetKeys("f9")
    store = tmp_path / "store"
    with in_process_router() as ep, Fleet(tmp_path) as fleet, client(ep) as s:
        w = FusedWatcher(s, keys)
        tap = MapTap(s, keys)
        try:
            fuse_args = ["fuse", "--connect", ep, "--fleet", keys.fleet, "--store", store]
            fleet.start("fuse", fuse_args)
            fleet.wait_log("fuse", "fusion service ready", 30)
            for rid in ("r1", "r2"):
                fleet.start(rid, robot_args(rid, ep, keys.fleet, LOOP[rid], tmp_path, rate=6, heartbeat=1.0))
            w.wait_for(lambda m: m.robots == ("r1", "r2") and m.seq >= 4, 90, "r1 and r2, version 4")
            wait_until(lambda: (store / "snapshot.msgpack").is_file() and read_store(store).fused is not None
                       and read_store(store).fused.robots == ("r1", "r2"),
                       20, "a stored fused map of both")  # fmt: skip
            fleet.kill9("fuse")
            stored = read_store(store)
            assert stored.from_snapshot and stored.fused is not None
            # the stored map is one the old service published
            published = w.wait_for(lambda m: m.seq == stored.version, 5, f"version {stored.version}")
            assert published.wireframe.almost_equal(stored.fused.wireframe, tol=1e-9, likelihood_tol=1e-9)
            seen_at_restart = tap.snapshot()
            n0 = w.count()
            t_restart = time.monotonic()
            fleet.start("fuse2", fuse_args)
            first, t_first = w.wait_for_timed(lambda m: True, 30,
                                              "the restarted service's first map", since=n0)
            record(record_property, "fusion_restart_first_map_s", round(t_first - t_restart, 3))
            assert first.seq == stored.version
            assert first.robots == stored.fused.robots
            assert first.wireframe.almost_equal(stored.fused.wireframe, tol=1e-9, likelihood_tol=1e-9)
            record(record_property, "fusion_restart_equal_edges",
                   f"{first.wireframe.n_edges}/{stored.fused.wireframe.n_edges}")
            # it catches up: every robot's map as new as what the robots had sent at the restart
            def caught_up() -> bool:
                have = stats_robot_keys(query_stats(s, keys))
                return all(have.get(r, (-1, -1)) >= k for r, k in seen_at_restart.items())

            wait_until(caught_up, 30, "the restarted fusion service to catch up")
            record(record_property, "fusion_restart_catch_up_s", round(time.monotonic() - t_restart, 3))
            newer = w.wait_for(lambda m: m.seq > stored.version, 30, "a newer version", since=n0)
            assert newer.robots == ("r1", "r2")
        finally:
            tap.close()
            w.close()
        assert fleet.stop("fuse2", signal.SIGTERM, timeout=20) == 0, fleet.log("fuse2")
    assert "resumed fused v" in fleet.log("fuse2") and "Traceback" not in fleet.log("fuse2")


# ---------------------------------------------------------------------- the router dies
def test_router_kill9_and_restart_every_process_reconnects_and_nothing_is_lost(
    tmp_path: Path, record_property
):
    """The router (a `wiremap router` process) is killed with SIGKILL and restarted on the same
    port while two robots map: the robots and the fusion service reconnect by themselves, the
    fused map updates again (new versions, nobody stale), and after the robots stop the fusion
    service holds each robot's last map (its seq = the robot's maps_sent)."""
    keys = FleetKeys("rr")
    ep = tcp_endpoint(free_port())
    router_args = ["router", "--listen", ep]
    with Fleet(tmp_path) as fleet:
        fleet.start("router", router_args)
        fleet.wait_log("router", "listening on", 30)
        fleet.start("fuse", ["fuse", "--connect", ep, "--fleet", keys.fleet])
        for rid in ("r1", "r2"):
            fleet.start(rid, robot_args(rid, ep, keys.fleet, LOOP[rid], tmp_path, rate=5, heartbeat=1.0))
        with client(ep, timeout=30) as s:
            w = FusedWatcher(s, keys)
            try:
                before = w.wait_for(lambda m: m.robots == ("r1", "r2") and not m.meta.get("stale"), 90,
                                    "r1 and r2")
                pre = stats_robot_keys(wait_until(lambda: query_stats(s, keys), 10, "stats"))
                t_kill = fleet.kill9("router")
                fleet.start("router2", router_args)
                fleet.wait_log("router2", "listening on", 30)
                t_restart = time.monotonic()
                n0 = w.count()
                # the fused map flows again, both robots alive, both robots' maps moving on
                w.wait_for(lambda m: m.robots == ("r1", "r2") and not m.meta.get("stale"), 60,
                           "a fused map after the restart", since=n0)  # fmt: skip

                def recovered() -> bool:
                    have = stats_robot_keys(query_stats(s, keys))
                    return all(have.get(r, (-1, -1)) > pre[r] for r in ("r1", "r2"))

                wait_until(recovered, 60, "new robot maps in the fusion service after the router restart")
                now = time.monotonic()
                record(record_property, "router_restart_recovery_s", round(now - t_restart, 3))
                record(record_property, "router_kill_to_recovered_s", round(now - t_kill, 3))
                newer = w.wait_for(lambda m: m.seq > before.seq, 60, "a newer fused version", since=n0)
                assert newer.robots == ("r1", "r2")
                # stop the robots; the fusion service must end with each one's last map
                for rid in ("r1", "r2"):
                    assert fleet.stop(rid, signal.SIGTERM, timeout=20) == 0, fleet.log(rid)
                sent = {r: json.loads((tmp_path / f"{r}.status.json").read_text()) for r in ("r1", "r2")}
                wait_until(lambda: {r: k[1] for r, k in stats_robot_keys(query_stats(s, keys)).items()}
                           == {r: st["maps_sent"] for r, st in sent.items()}, 20,
                           "the fusion service to hold each robot's last map")  # fmt: skip
                record(record_property, "router_restart_last_seq",
                       {r: st["maps_sent"] for r, st in sent.items()})
            finally:
                w.close()
        assert fleet.stop("fuse", signal.SIGTERM, timeout=20) == 0, fleet.log("fuse")
    for name in ("fuse", "r1", "r2"):
        assert "Traceback" not in fleet.log(name), fleet.log(name)
