"""The fusion service process: the Zenoh shell around :class:`FusionState` (``wiremap fuse``).

:func:`serve` runs a :class:`FusionService` on an open session until a stop flag is set; see
:mod:`agents.fleet.fusion` for what it subscribes to, publishes and answers.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from agents.errors import UserError
from agents.fleet import validate
from agents.fleet.fusion.budget import BudgetConfig, WorkBudget
from agents.fleet.fusion.codec import decode_message, encode_message
from agents.fleet.fusion.frames import FramesConfig
from agents.fleet.fusion.intake import DropLog, InputLimits, Intake, by_key
from agents.fleet.fusion.islands import IslandShell, frames_section
from agents.fleet.fusion.quarantine import QuarantineConfig
from agents.fleet.fusion.state import FusionConfig, FusionState
from agents.fleet.fusion.stats import LatencyWindow
from agents.fleet.fusion.store import StoreWriter
from agents.fleet.proc import freeze_heap, rss_kb


@dataclass
class ServeOptions:
    """Options of the fusion service process (``wiremap fuse``).

    store : state directory (resume from it, save to it); None: memory only.
    rrd : Rerun recording file; None: no recording.
    serve_viewer : also serve the recording live on this port (needs ``rrd``).
    world : a world name or file, to draw the ground truth in the recording.
    recording_id : Rerun recording id (processes sharing it make one recording).
    heartbeat_s : re-publish the current fused map at least this often (idempotent).
    min_interval_s : fuse at most this often (maps arriving meanwhile are batched).
    save_interval_s : write the store at most this often (each write fsyncs; the last state
        is always written at exit, so a crash (kill -9) loses at most this much, which the
        robots' next heartbeat maps restore). 0: on every change. The writes happen in a
        background thread (:class:`StoreWriter`).
    full_after_s : when no robot map has changed for this long and the fused map is not the
        full path's (:attr:`FusionState.converged`), recompute it by the full path.
    latency_summary_s : recompute the latency percentiles of ``fused/stats`` at most this often
        (the counters themselves are always current).
    align_wait_s : an ICP re-alignment (the slow path) runs after a publish when no map is
        waiting, or when none has run for this long even though maps keep waiting.
    limits : :class:`InputLimits` (what is accepted from the bus).
    reset : start empty when the store cannot be recovered (its files moved aside) instead of
        refusing to start (:class:`~agents.fleet.fusion.store.StoreDamaged`).
    drop_log_s : at most one "dropped ..." line per this many seconds (:class:`DropLog`).
    config : :class:`FusionConfig`.
    frames : :class:`FramesConfig` (robots of unknown start pose: anchor, retry schedule).
    quarantine : :class:`QuarantineConfig` (maps inconsistent with their robot's history or the
        fleet are kept aside; None: off).
    budget : :class:`BudgetConfig` (a robot's maps may cost this much fusion CPU; None: off).
    """

    store: str | None = None
    rrd: str | None = None
    serve_viewer: int | None = None
    world: str | None = None
    recording_id: str | None = None
    heartbeat_s: float = 3.0
    min_interval_s: float = 0.0
    save_interval_s: float = 1.0
    config: FusionConfig = field(default_factory=FusionConfig)
    limits: InputLimits = field(default_factory=InputLimits)
    drop_log_s: float = 5.0
    full_after_s: float = 0.5
    latency_summary_s: float = 1.0
    align_wait_s: float = 0.5
    reset: bool = False
    frames: FramesConfig = field(default_factory=FramesConfig)
    quarantine: QuarantineConfig | None = field(default_factory=QuarantineConfig)
    budget: BudgetConfig | None = field(default_factory=BudgetConfig)


MAX_ADMIN_BYTES = 256  # an admin query's payload (``forget=ID``), at most


class FusionService:
    """The Zenoh shell around :class:`FusionState` (see :func:`serve`)."""

    def __init__(
        self, session: Any, keys: Any, opts: ServeOptions, log: Callable[[str], None] | None = None
    ) -> None:
        import zenoh

        self._zenoh = zenoh
        self.session = session
        self.keys = keys
        self.opts = opts
        self.say = log or (lambda _s: None)
        self.state = (
            FusionState.load(opts.store, opts.config, limits=opts.limits, reset=opts.reset)
            if opts.store
            else FusionState(opts.config, limits=opts.limits)
        )
        self.state.quarantine_config = opts.quarantine
        self.state.budget = WorkBudget(opts.budget) if opts.budget is not None else None
        self.state.restart_by_token = True  # a robot's restart is learned from its liveliness token
        self._came_alive: list[str] = []  # tokens that appeared (zenoh thread -> main thread)
        self._forget_requests: list[
            tuple[str, Any]
        ] = []  # admin/forget queries (zenoh thread -> main thread)
        self._last_unproven = 0.0
        self.state.frames.config = opts.frames
        self.recorder: Any = None
        if opts.rrd:
            from agents.files.rerun_log import FleetRecorder

            self.recorder = FleetRecorder(opts.rrd, serve_port=opts.serve_viewer,
                                          recording_id=opts.recording_id)
            if opts.world:
                try:
                    from agents.sim.world import load_world

                    self.recorder.log_truth(load_world(opts.world).truth)
                except (UserError, OSError, ValueError) as exc:
                    self.say(f"cannot draw the world {opts.world!r}: {exc}")
        self.lock = threading.Lock()
        self.current: bytes | None = None  # the last published fused map (the queryable's answer)
        self.version_stamp_ns = 0
        self.intake = Intake(opts.limits)
        self.drops = DropLog(self._say_drop, opts.drop_log_s)
        self._side: dict[str, dict[str, bytes]] = {"pose": {}, "viz": {}}
        self._side_dropped = 0
        self._side_by: dict[str, int] = {}  # side_dropped by kind and reason
        self.alive: set[str] = set()
        self.seen_alive: set[str] = set()
        self._gone_during_query: set[str] = set()
        self.liveliness_ready = False
        self.stale: list[str] = []
        self.last_put = time.monotonic()
        self.last_fuse = 0.0
        self.last_say = 0.0
        self.dirty: set[str] = set()
        self.refuse = False  # fuse at the next iteration even without new maps (a new alignment)
        self.last_align = -math.inf
        self.unsaved: set[str] = set()
        self.last_save = 0.0
        self.save_due = False  # the store is behind for another reason than robot maps
        self.last_change = time.monotonic()  # when a robot map last changed
        self._lat_at = -math.inf
        self.timing: dict[str, float] = dict.fromkeys(
            ("wait", "decode", "fuse", "publish", "align", "other", "iterations"), 0.0
        )
        self._timed = 0.0  # of this iteration's time, spent in _fuse
        self.transport_ms = LatencyWindow(10_000)  # robot publish -> inbox, of maps that changed
        self.writer = StoreWriter(self.say) if opts.store else None
        self.unsaved.update(self.state.store_rewrite)  # damaged views found at start are written again
        for line in self.state.store_report:
            self.say(f"store: {line}")
        self.started = time.monotonic()
        self._stats_doc = b"{}"
        self._stats_at = -math.inf
        self._stats_version: tuple[int, tuple[str, ...]] = (-1, ())
        self._entities: list[Any] = []
        self.islands = IslandShell(session, keys, self.recorder, self.say)
        if self.state.version > 0 and self.state.robots:
            self.version_stamp_ns = time.time_ns()
            self.current = encode_message(self.state.fused_message(self.version_stamp_ns, self._meta()))
            self.say(
                f"resumed fused v{self.state.version} from {opts.store} ({len(self.state.robots)} robots)"
            )

    def _say_drop(self, line: str) -> None:
        self.say(line)
        if self.recorder is not None:
            self.recorder.log_text(self.state.sim_time(), line, level="WARN")

    # ------------------------------------------------------------------ zenoh callbacks (zenoh threads)
    def _on_map(self, sample: Any) -> None:
        key = str(sample.key_expr)
        payload = sample.payload
        reason = self.intake.put(key, payload)
        if reason is not None:
            self.drops.note(reason, key, f"{len(payload)} bytes")

    def _on_side(self, kind: str, max_bytes: int, sample: Any) -> None:
        key = str(sample.key_expr)
        payload = sample.payload
        rid = self.keys.robot_of(key)
        with self.lock:
            slot = self._side[kind]
            reason = (
                "bad_key" if rid is None
                else "oversized" if len(payload) > max_bytes
                else "too_many_keys" if rid not in slot and len(slot) >= self.opts.limits.max_keys
                else None
            )
            if reason is not None:
                self._side_dropped += 1
                self._side_by[f"{kind}_{reason}"] = self._side_by.get(f"{kind}_{reason}", 0) + 1
                return
            slot[rid] = payload.to_bytes()  # only the latest per robot matters

    def _on_pose(self, sample: Any) -> None:
        self._on_side("pose", self.opts.limits.pose_bytes, sample)

    def _on_viz(self, sample: Any) -> None:
        self._on_side("viz", self.opts.limits.viz_bytes, sample)

    def _on_query(self, query: Any) -> None:
        with self.lock:
            data = self.current
        if data is not None:
            query.reply(self.keys.fused_map, data)

    def _on_stats_query(self, query: Any) -> None:
        with self.lock:
            data = self._stats_doc
        query.reply(self.keys.fusion_stats, data, encoding=self._zenoh.Encoding.APPLICATION_JSON)

    def _on_forget(self, query: Any) -> None:
        """``admin/forget`` (payload ``forget=ID``): answered by the main thread (:meth:`_forget`)."""
        payload = query.payload
        rid = payload.to_bytes()[:MAX_ADMIN_BYTES].decode("utf-8", "replace") if payload is not None else ""
        with self.lock:
            if len(self._forget_requests) < 16:
                self._forget_requests.append((rid, query))
                return
        query.reply_err(b"busy")

    def _forget(self) -> None:
        """Serve the waiting ``admin/forget`` queries and forget robot ids that never became
        plausible (:meth:`FusionState.forget_implausible`, checked every 5 s)."""
        st = self.state
        with self.lock:
            requests, self._forget_requests = self._forget_requests, []
        for text, query in requests:
            try:
                _, rid = validate.admin_request(text)
            except validate.Invalid as exc:
                answer = {"ok": False, "error": exc.detail}
            else:
                had = st.forget(rid, "forgotten by the fleet's admin")
                answer = {"ok": True, "robot": rid, "had_map": had}
                self._forgotten(rid, "by the admin")
            with query:
                query.reply(self.keys.admin_forget, json.dumps(answer).encode())
        if time.monotonic() - self._last_unproven >= 5.0:
            self._last_unproven = time.monotonic()
            for rid in st.forget_implausible(time.time_ns()):
                self._forgotten(rid, "automatically: it never sent a plausible map")

    def _forgotten(self, rid: str, how: str) -> None:
        self.say(f"forgot robot {rid} {how}")
        self.dirty.add(rid)  # a fuse without it
        self.refuse = True
        self.save_due = True
        self.unsaved.discard(rid)
        if self.recorder is not None:
            self.recorder.log_text(self.state.sim_time(), f"forgot robot {rid} {how}")

    def _on_alive(self, sample: Any) -> None:
        rid = self.keys.robot_of(str(sample.key_expr))
        if rid is None:
            return
        with self.lock:
            if sample.kind == self._zenoh.SampleKind.PUT:
                if rid not in self.alive:
                    self._came_alive.append(rid)
                self.alive.add(rid)
                self.seen_alive.add(rid)
                self._gone_during_query.discard(rid)
            else:
                self.alive.discard(rid)
                self._gone_during_query.add(rid)

    # ------------------------------------------------------------------ main thread
    def start(self) -> None:
        """Declare everything. The liveliness tokens alive now are fetched before the first
        publication (a liveliness query, ``wait`` up to 2 s), so that a resumed map's stale
        list is right from the start: a robot is *stale* when the fused map holds its walls
        and no token of it is alive (after the start-up query)."""
        s = self.session
        # liveliness first, so the alive set is complete when the first maps come in
        self._entities.append(
            s.liveliness().declare_subscriber(self.keys.all_alive, self._on_alive, history=True)
        )
        with self.lock:
            self._gone_during_query.clear()
        try:
            for reply in s.liveliness().get(self.keys.all_alive, timeout=2.0):
                ok = reply.ok
                rid = None if ok is None else self.keys.robot_of(str(ok.key_expr))
                if rid is not None:
                    with self.lock:
                        if rid not in self._gone_during_query:
                            self.alive.add(rid)
                            self.seen_alive.add(rid)
        except self._zenoh.ZError as exc:  # pragma: no cover - the subscriber still works
            self.say(f"liveliness query failed: {exc}")
        self.liveliness_ready = True
        self._entities.append(s.declare_queryable(self.keys.fused_map, self._on_query, complete=True))
        self._entities.append(s.declare_queryable(self.keys.fusion_stats, self._on_stats_query,
                                                  complete=True))
        admin = getattr(self.keys, "admin_forget", None)  # a regional fuser's keys have none (yet)
        if admin is not None:
            self._entities.append(s.declare_queryable(admin, self._on_forget, complete=True))
        self._entities.append(s.declare_subscriber(self.keys.all_maps, self._on_map))
        if self.recorder is not None:
            # poses and scans only feed the recording: without one, 10 Hz x robots of callbacks
            # (each taking the interpreter lock from the fusion loop) would be for nothing
            self._entities.append(s.declare_subscriber(self.keys.all_poses, self._on_pose))
            self._entities.append(s.declare_subscriber(self.keys.all_viz, self._on_viz))
        self._update_stale(publish=False)
        if self.current is not None:
            self.current = encode_message(self.state.fused_message(self.version_stamp_ns, self._meta()))
            self._put(self.current)
        self._update_stats(force=True)

    def _meta(self) -> dict[str, Any]:
        return {"stale": list(self.stale), "t": self.state.sim_time()}

    def _put(self, data: bytes) -> None:
        self.session.put(self.keys.fused_map, data, congestion_control=self._zenoh.CongestionControl.BLOCK)
        self.last_put = time.monotonic()

    def _publish_new_version(self) -> None:
        st = self.state
        self.version_stamp_ns = time.time_ns()
        data = encode_message(st.fused_message(self.version_stamp_ns, self._meta()))
        with self.lock:
            self.current = data
        self._update_stats(force=True)  # before the put: whoever sees the map sees its counters
        self._put(data)
        self.islands.publish(st, self.version_stamp_ns)
        lat = st.take_latencies(time.time_ns())
        if self.recorder is not None:
            self.recorder.log_fused(st.sim_time(), st.fused, st.fused_robots, st.version,
                                    max(lat) if lat else None)
        now = time.monotonic()
        if now - self.last_say >= 1.0:
            self.last_say = now
            self.say(
                f"fused v{st.version}: {st.fused.n_vertices} vertices, {st.fused.n_edges} edges, "
                f"{len(data)} bytes, robots {' '.join(st.fused_robots)}"
            )

    def _take(self, items: list[tuple[str, bytes, int]]) -> None:
        st = self.state
        with self.lock:
            came, self._came_alive = self._came_alive, []
        for rid in came:
            st.note_alive(rid, time.time_ns())
        now_ns = time.time_ns()
        for rid in st.release_held(now_ns):  # maps that waited for their robot's work budget
            self.dirty.add(rid)
            self.last_change = time.monotonic()
        # of each robot key's payloads only the newest is decoded (FusionState.offer_latest)
        for key, group in by_key(items):
            rid = self.keys.robot_of(key)
            if rid is None:
                for _ in group:
                    st.reject_key(key)
                    if st.last_drop is not None:
                        self._note_drop(key, None, st.last_drop)
                continue
            taken = st.offer_latest([data for data, _ in group], rid, now_ns)
            if taken.changed:
                self.dirty.add(rid)
                self.last_change = time.monotonic()
                # robot publish -> in the fusion service's inbox (transport and the robot's own put)
                arrived_ns = group[taken.index][1]
                self.transport_ms.extend([max(0.0, (arrived_ns - st.robots[rid].message.stamp_ns) / 1e6)])
            for drop in taken.drops:
                self._note_drop(key, rid, drop)

    def _note_drop(self, key: str, rid: str | None, drop: tuple[str, str, str]) -> None:
        counter, reason, detail = drop
        self.drops.note(counter, key, f"{reason}: {detail}")
        if counter == "quarantined" and rid is not None and self.recorder is not None:
            q = self.state.quarantine.maps.get(rid)
            if q is not None:
                m = decode_message(q.raw)
                t = float(m.meta.get("t", 0.0)) if isinstance(m.meta.get("t"), (int, float)) else 0.0
                self.recorder.log_quarantine(rid, t, f"{reason}: {detail}", m.wireframe.transformed(m.origin))

    def _update_stale(self, publish: bool = True) -> None:
        """Recompute the stale list; on a change re-publish the same version with the new
        metadata and mark the robots in the recording."""
        st = self.state
        if not self.liveliness_ready:
            return
        with self.lock:
            stale = sorted(r for r in st.fused_robots if r not in self.alive)
        if stale == self.stale:
            return
        went, back = sorted(set(stale) - set(self.stale)), sorted(set(self.stale) - set(stale))
        self.stale = stale
        if went:
            self.say(f"stale robots: {' '.join(went)} (liveliness token gone; their last maps are kept)")
        if back:
            self.say(f"robots back: {' '.join(back)}")
        if self.recorder is not None:
            t = st.sim_time()
            for rid in went + back:
                if rid in st.robots:
                    self.recorder.log_robot_status(rid, t, rid in went, st.robot_in_fleet(rid))
        if publish and self.current is not None:
            # same version and stamp, new metadata: robots that left are flagged
            data = encode_message(st.fused_message(self.version_stamp_ns, self._meta()))
            with self.lock:
                self.current = data
            self._update_stats(force=True)
            self._put(data)

    def stats_doc(self) -> dict[str, Any]:
        """The counters document served on ``fused/stats`` (JSON)."""
        st = self.state
        self._sync_counters()
        fresh = self._fresh_latency()
        with self.lock:
            alive = sorted(self.alive)
        return {
            "version": st.version,
            "fused": {"vertices": st.fused.n_vertices, "edges": st.fused.n_edges,
                      "robots": list(st.fused_robots)},
            "stale": list(self.stale),
            "alive": alive,
            "robots": {
                r: {"seq": e.key[1], "boot": e.key[0], "stamp_ns": int(e.message.stamp_ns)}
                for r, e in sorted(st.robots.items())
            },
            "stats": st.stats.as_dict(fresh),
            "converged": st.converged,
            "quarantine": st.quarantine.summary(),
            "forgotten": dict(sorted(st.forgotten.items())),
            **({"frames": frames_section(st)} if st.frames.active else {}),
            "transport_ms": self.transport_ms.summary(fresh),
            "queued_bytes": self.intake.queued_bytes,
            "store": self.store_health(),
            "drop_log_lines": self.drops.lines,
            "rss_kb": rss_kb(),
            "pid": os.getpid(),
            "uptime_s": round(time.monotonic() - self.started, 3),
        }

    def store_health(self) -> dict[str, Any]:
        """The store's health for ``fused/stats`` and ``watch``: ``ok`` false while writes fail
        (disk full, read-only), the last error, the version on disk, what start-up recovered."""
        w = self.writer
        if w is None:
            return {"ok": True, "enabled": False}
        return {
            "ok": w.ok,
            "enabled": True,
            "errors": w.errors,
            "error": w.last_error or None,
            "written_version": w.written_version,
            "behind": max(0, self.state.version - w.written_version),
            "recovered": list(self.state.store_report),
        }

    def _fresh_latency(self) -> bool:
        """Whether the latency percentiles are due for a recomputation."""
        now = time.monotonic()
        if now - self._lat_at >= self.opts.latency_summary_s:
            self._lat_at = now
            return True
        return False

    def _sync_counters(self) -> None:
        s = self.state.stats
        s.oversized, s.rate_limited, s.overflow = (
            self.intake.oversized,
            self.intake.rate_limited,
            self.intake.overflow,
        )
        with self.lock:
            s.side_dropped = self._side_dropped
            s.side_dropped_by = dict(self._side_by)

    def _side_drop(self, reason: str) -> None:
        with self.lock:
            self._side_dropped += 1
            self._side_by[reason] = self._side_by.get(reason, 0) + 1

    def _update_stats(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._stats_at < 0.2:
            return
        self._stats_at = now
        self._stats_version = (self.state.version, tuple(self.stale))
        data = json.dumps(self.stats_doc()).encode()
        with self.lock:
            self._stats_doc = data

    def poll(self, timeout: float = 0.05) -> None:
        """One iteration: take every map that arrived (the whole queue), fuse once (the fast
        path), publish once, hand the store to the writer thread, log. When no map has
        changed for ``full_after_s`` and the fused map is not the full path's, the full path
        runs instead (at most once per quiet period: afterwards it is converged)."""
        st = self.state
        clock = time.perf_counter
        t0 = clock()
        if self.dirty or self.refuse:
            # a fuse is due once min_interval_s has passed since the last: wait no longer
            due = self.last_fuse + self.opts.min_interval_s - time.monotonic()
            timeout = min(timeout, max(due, 0.0))
        items = self.intake.drain_timed(timeout)
        t1 = clock()
        self._take(items)
        t2 = clock()
        self.timing["wait"] += t1 - t0
        self.timing["decode"] += t2 - t1
        now = time.monotonic()
        if (self.dirty or self.refuse) and now - self.last_fuse >= self.opts.min_interval_s:
            self.last_fuse = now
            changed = sorted(self.dirty)
            self.dirty.clear()
            self.refuse = False
            self._fuse(full=False, now=now, max_realign=0)
            self.unsaved.update(changed)
            if self.recorder is not None:
                for rid in changed:
                    if rid in st.robots and st.frames.in_fleet(rid):
                        t = float(st.robots[rid].message.meta.get("t", 0.0))
                        self.recorder.log_robot_map(rid, t, st.robot_in_fleet(rid))
        elif (
            not self.dirty
            and not self.refuse
            and st.robots
            and not st.converged
            and now - self.last_change >= self.opts.full_after_s
        ):
            self._fuse(full=True, now=now)
            self.save_due = True  # the alignments (and maybe the map) changed
        if st.wanted and (self.intake.empty or now - self.last_align >= self.opts.align_wait_s):
            # the slow path after the publish: the maps just fused did not wait for ICP, nor
            # do maps already waiting (unless alignments have waited align_wait_s); the next
            # fuse applies the new alignment
            t = time.perf_counter()
            self.last_align = now
            if st.realign(now=now, limit=1):
                self.refuse = True  # fuse again even if no map arrives
            self.timing["align"] += time.perf_counter() - t
            self._timed += time.perf_counter() - t
        if self.writer is not None and not self.writer.ok and not self.save_due:
            self.save_due = True  # a failed write (disk full, read-only) is retried with everything
            self.unsaved.update(st.robots)
        if st.frames.active:  # robots of unknown start pose: one registration attempt when idle
            t = time.perf_counter()
            if self.islands.step(st, now, idle=self.intake.empty and not self.dirty):
                self.refuse = True
                self.save_due = True
            if time.monotonic() - self.islands.last_pub >= 1.0:
                self.islands.publish(st, time.time_ns())
            self._timed += time.perf_counter() - t
        if (
            self.opts.store
            and (self.unsaved or self.save_due)
            and time.monotonic() - self.last_save >= self.opts.save_interval_s
        ):
            self._save_async()
        self._poll_side_channels()
        self._forget()
        self._update_stale()
        if self.current is not None and time.monotonic() - self.last_put > self.opts.heartbeat_s:
            self._put(self.current)  # maps are whole states: re-publishing is idempotent
        self.drops.flush()
        # at once when the published map changed (a querier that saw it sees its counters),
        # otherwise at most every 0.2 s
        self._update_stats(force=self._stats_version != (self.state.version, tuple(self.stale)))
        self.timing["other"] += clock() - t2 - self._timed
        self._timed = 0.0
        self.timing["iterations"] += 1

    def _fuse(self, full: bool, now: float, max_realign: int | None = None) -> None:
        t0 = time.perf_counter()
        changed = self.state.fuse(full=full, now=now, max_realign=max_realign)
        t1 = time.perf_counter()
        if changed:
            self._update_stale(publish=False)  # the new version carries the right stale list
            self._publish_new_version()
        t2 = time.perf_counter()
        self.timing["fuse"] += t1 - t0
        self.timing["publish"] += t2 - t1
        self._timed += t2 - t0

    def timing_line(self) -> str:
        """Where the main loop's time went (seconds in total): waiting for maps, decoding,
        fusing, publishing, the rest."""
        t = self.timing
        parts = " ".join(f"{k} {t[k]:.2f}" for k in ("wait", "decode", "fuse", "publish", "align", "other"))
        tr = self.transport_ms.summary()
        transport = (
            ""
            if tr["p50"] is None
            else f"; robot publish -> inbox ms: p50 {tr['p50']:.1f} p99 {tr['p99']:.1f}"
        )
        return (
            f"main loop: {int(t['iterations'])} iterations, {self.state.stats.fuses} fuses; seconds: {parts}"
            f"{transport}"
        )

    def _save_async(self) -> None:
        assert self.opts.store is not None
        self._sync_counters()
        job = self.state.store_job(self.opts.store, sorted(self.unsaved), self.version_stamp_ns,
                                   self._fresh_latency())
        if self.writer is not None:
            self.writer.submit(job)
        else:  # pragma: no cover - a store always has a writer
            job.write()
        self.unsaved.clear()
        self.save_due = False
        self.last_save = time.monotonic()

    def _poll_side_channels(self) -> None:
        from agents.fleet.bus import decode_pose, decode_viz
        from agents.fleet.validate import Invalid

        st = self.state
        with self.lock:
            raw_poses, raw_viz = self._side["pose"], self._side["viz"]
            self._side = {"pose": {}, "viz": {}}
        poses: dict[str, dict[str, Any]] = {}
        viz: dict[str, dict[str, Any]] = {}
        for kind, raw, out, decode in (("pose", raw_poses, poses, decode_pose),
                                       ("viz", raw_viz, viz, decode_viz)):
            for rid, data in raw.items():
                try:
                    out[rid] = decode(data)  # every field checked (agents.fleet.validate)
                except Invalid as exc:
                    self._side_drop(f"{kind}_{exc.reason}")
                    self.drops.note("side_dropped", f"robots/{rid}/{kind}", str(exc))
        if self.recorder is None:
            return
        for rid, p in sorted(poses.items()):
            origin = st.robots[rid].message.origin if rid in st.robots else None
            est = p["fleet"] if origin is None else origin.compose(p["odom"])
            self.recorder.log_robot_pose(rid, p["t"], est, p["truth"])
        for rid, v in sorted(viz.items()):
            if rid in st.robots:
                m = st.robots[rid].message
                self.recorder.log_robot_viz(rid, v["t"], m.origin, v["pose"], v["scan"], v["particles"],
                                            v["weights"])

    def close(self) -> None:
        """Fuse and publish the maps still queued by the full path (the final map is the
        deterministic one), undeclare everything, write the store (after whatever the writer
        thread still had), close the recording."""
        st = self.state
        try:
            self._take(self.intake.drain_timed(0.0))
            if st.robots and (self.dirty or self.refuse or not st.converged):
                self.dirty.clear()
                self._fuse(full=True, now=time.monotonic())
        finally:
            for ent in reversed(self._entities):
                try:
                    ent.undeclare()
                except Exception:  # already undeclared or session closed
                    pass
            self._entities.clear()
            self._sync_counters()
            self.drops.flush(force=True)
            self.say(self.timing_line())
            if self.writer is not None:
                self.writer.close()
            if self.opts.store:
                try:
                    st.save(self.opts.store, None, self.version_stamp_ns)
                except OSError as exc:  # disk full, read-only: one line, a clean exit
                    st.exit_error = f"cannot write the store {self.opts.store} at exit: {exc.strerror or exc}"
                    self.say(st.exit_error)
            if self.recorder is not None:
                self.recorder.close()


def serve(
    session: Any, keys: Any, opts: ServeOptions, stop: threading.Event,
    log: Callable[[str], None] | None = None
) -> FusionState:
    """Run the fusion service on an open Zenoh session until ``stop`` is set.

    Maps arrive through a callback into the bounded :class:`Intake` (zenoh's thread only
    checks sizes and rates and copies bytes); poses and visualisation through callbacks that
    keep the latest payload per robot. The main thread decodes, fuses, publishes, stores and
    logs; the queryables' callbacks answer with the last published bytes (fused map) and the
    last counters document (``fused/stats``) under a lock. Returns the final state (saved when
    ``opts.store`` is set).
    """
    svc = FusionService(session, keys, opts, log)
    try:
        svc.start()
        freeze_heap()
        svc.say("fusion service ready")
        while not stop.is_set():
            svc.poll(0.05)
    finally:
        svc.close()
    return svc.state
