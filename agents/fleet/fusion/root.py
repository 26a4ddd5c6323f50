"""The root fuser (``wiremap fuse --of-groups NAME,NAME|*``): merges the regional fusers'
partial maps (``wiremap/<fleet>/groups/<NAME>/map``) into the fleet's fused map.

* subscribes to the partials (each group's newest by ``(meta.boot, version)``, so a restarted
  or taken-over group supersedes the old one whatever its version), to the robots' liveliness
  tokens (the stale list, as the one-process service) and to the fusers' tokens
  (``fusers/<NAME>``: a group whose fuser is gone keeps its last partial in the map, listed in
  ``meta.fusers_down``, until a takeover or a restart publishes again);
* publishes ``wiremap/<fleet>/fused/map`` (:class:`RootState`: the one-process fold when the
  groups are the fold's subtrees, ``meta.exact``), on every change (at most every
  ``min_interval_s``, the newest partial of each group waiting in the inbox, not yet part of the
  state, and fused on close) and every ``heartbeat_s``,
  answers queries for it and for its counters (``fused/stats``: versions, per-level latency,
  the groups' versions);
* latency: ``latency_ms`` from each robot map's publish (the stamps a partial carries) to the
  fused publish that includes it (end to end, the figure of the one-process service);
  ``root_ms`` from a partial's publish to that fused publish (the root's level); with
  ``--store DIR`` the end-to-end samples go to ``DIR/latency.log`` and the map to
  ``DIR/fused.wfm`` and ``DIR/state.json`` (as the one-process store's views), written once a
  second by a background thread (the loop never waits for the disk).

**Several roots** (failover; the choice made here). Any number of roots may run; each holds the
liveliness token ``wiremap/<fleet>/fusers/root/<boot>`` (``boot``: its start, ns) and the
*oldest* live one is **active**: it alone publishes ``fused/map``, answers its queryable and
``fused/stats`` and holds ``fusers/root``. The others are **standbys**: they keep the latest
bytes of each group's partial and of the fused map (nothing decoded, nothing merged: a
standby costs a callback per partial) and take over when every older root's token is gone
(kill -9: milliseconds; a frozen process: the Zenoh lease). On takeover a standby decodes what
it kept, folds the partials (the same fold, so the same map) and publishes it with the version
after the last one the old root published, so a subscriber that keeps the highest version
follows it. A root restarted later is the youngest, so it stays a standby (no flapping); two
roots active across a healed partition: the younger steps down when it sees the older's token.

**Restart from the store.** With ``--store DIR`` a root starts from ``DIR/fused.wfm`` (the
codec's CRC checks it; written atomically): it serves that map and continues its version
before any partial arrives. An unreadable file is one line and exit 2, unless ``--reset`` (the
file moved aside, the version restarted from the wall clock in ms so that it never goes back).
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agents.errors import UserError
from agents.fleet.fusion.codec import decode_message, encode_message
from agents.fleet.fusion.stats import LatencyWindow
from agents.fleet.fusion.store import StoreWriter, append_latency_log
from agents.fleet.fusion.tree import GroupKeys, RootState
from agents.fleet.proc import freeze_heap, rss_kb
from mapping.wireframe import Wireframe

ROOT_NAME = "root"


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


#: A robot alive this long that no group's partial includes is listed as ``uncovered``.
UNCOVERED_AFTER_S = 10.0


@dataclass
class _RootStoreJob:
    """The root's store files to write (``latency.log`` rows, ``fused.wfm``, ``state.json``,
    each fsynced), as a job for :class:`~agents.fleet.fusion.store.StoreWriter`: written in a
    background thread so that the root's loop never waits for a disk (they were written in the
    loop once a second, a stall of tens of milliseconds in the root's latency)."""

    store: Path
    rows: list[tuple[int, float, int]]
    fused: bytes | None
    state: bytes
    version: int = 0

    def then(self, later: _RootStoreJob) -> _RootStoreJob:
        """This job and a later one as one: the newest files, every latency row of both."""
        return _RootStoreJob(self.store, self.rows + later.rows,
                             later.fused if later.fused is not None else self.fused, later.state,
                             later.version)

    def write(self) -> None:
        write_root_store(self.store, self.rows, self.fused, self.state)


def write_root_store(store: Path, rows: list[tuple[int, float, int]], fused: bytes | None,
                     state: bytes) -> None:
    """The root's store files: latency rows appended, the fused map and the state replaced."""
    store.mkdir(parents=True, exist_ok=True)
    if rows:
        append_latency_log(store, rows)
    if fused is not None:
        _atomic_write(store / "fused.wfm", fused)
    _atomic_write(store / "state.json", state)


def read_root_store(store: str | os.PathLike[str], reset: bool = False) -> bytes | None:
    """The fused map a root's ``--store`` holds (``fused.wfm``), None when there is none.
    Unreadable: :class:`UserError` (one line, exit 2), or with ``reset`` the file is moved to
    ``damaged-<ns>/`` and None returned."""
    path = Path(store) / "fused.wfm"
    if not path.is_file():
        return None
    try:
        data = path.read_bytes()
        msg = decode_message(data)
    except (OSError, ValueError) as exc:
        if not reset:
            raise UserError(
                f"--store {store}: fused.wfm is unreadable ({exc}); --reset moves it aside") from None
        aside = Path(store) / f"damaged-{time.time_ns()}"
        aside.mkdir(parents=True, exist_ok=True)
        os.replace(path, aside / "fused.wfm")
        return None
    from wire_codec.message import MessageKind

    if msg.kind != MessageKind.FUSED_MAP:
        if not reset:
            raise UserError(f"--store {store}: fused.wfm is not a fused map; --reset moves it aside")
        return None
    return data


class RootService:
    """The root fuser's Zenoh shell around :class:`RootState`."""

    def __init__(
        self,
        session: Any,
        keys: Any,
        groups: list[str] | None,
        threshold: float | None = None,
        heartbeat_s: float = 3.0,
        store: str | None = None,
        log: Callable[[str], None] | None = None,
        reset: bool = False,
        recording: dict[str, Any] | None = None,
        min_interval_s: float = 0.0,
    ) -> None:
        import zenoh

        self._zenoh = zenoh
        self.session = session
        self.keys = keys
        self.tree = GroupKeys(keys.prefix)
        self.groups = set(groups) if groups else None
        self.state = RootState(threshold)
        self.heartbeat_s = heartbeat_s
        # fuse at most this often: partials arriving meanwhile wait in the inbox (the newest of
        # each group, undecoded; the state's partials stay those of the map served)
        self.min_interval_s = max(0.0, float(min_interval_s))
        self.last_fuse = -math.inf
        self.store = Path(store) if store else None
        self.say = log or (lambda _s: None)
        self.lock = threading.Lock()
        self.cond = threading.Condition(self.lock)
        self.inbox: dict[str, tuple[bytes, int]] = {}
        self.alive: set[str] = set()
        self.fusers: set[str] = set()
        self.fusers_seen: set[str] = set()
        self.current: bytes | None = None
        self.stamp_ns = 0
        self.last_put = 0.0
        self.latency = LatencyWindow(100_000)
        self.root_ms = LatencyWindow(100_000)
        self.transport_ms = LatencyWindow(10_000)  # partial publish -> root inbox
        self.lat_total = 0
        self._unsaved: list[tuple[int, float, int]] = []
        self._saved_at = 0.0
        self._writer: StoreWriter | None = None  # the store's writes, off the loop
        self._stats_doc = b"{}"
        self._entities: list[Any] = []
        self.received = 0
        self.started = time.monotonic()
        self.boot = time.time_ns()
        self.active = False
        self.roots: set[int] = set()  # boots of the live roots (their tokens), ours included
        self._fused_raw: bytes | None = None  # the active root's latest fused map (standby)
        self._active_entities: list[Any] = []
        self.alive_since: dict[str, float] = {}
        self.uncovered: list[str] = []
        self.takeovers = 0
        self.recorder: Any = None
        rec = recording or {}
        if rec.get("rrd"):  # the fused map (a regional fuser records its own robots)
            from agents.files.rerun_log import FleetRecorder

            self.recorder = FleetRecorder(rec["rrd"], serve_port=rec.get("serve_viewer"),
                                          recording_id=rec.get("recording_id"))
            if rec.get("world"):
                try:
                    from agents.sim.world import load_world

                    self.recorder.log_truth(load_world(rec["world"]).truth)
                except (UserError, OSError, ValueError) as exc:
                    self.say(f"cannot draw the world {rec['world']!r}: {exc}")
        if self.store is not None:
            had = (self.store / "fused.wfm").is_file()
            data = read_root_store(self.store, reset)
            if data is not None:  # serve the stored map and continue its version
                self._resume(data)
            elif had:  # moved aside (--reset): a version that never goes back
                self.state.version = time.time_ns() // 1_000_000

    def _resume(self, data: bytes) -> None:
        msg = decode_message(data)
        self.state.version = max(self.state.version, int(msg.seq))
        self.state.fused, self.state.fused_robots = msg.wireframe, tuple(msg.robots)
        self.current = data
        self.stamp_ns = int(msg.stamp_ns)

    # zenoh threads
    def _on_partial(self, sample: Any) -> None:
        g = self.tree.group_of(str(sample.key_expr))
        if g is None or (self.groups is not None and g not in self.groups):
            return
        data = sample.payload.to_bytes()
        with self.cond:
            self.inbox[g] = (data, time.time_ns())  # whole states: the latest is enough
            self.received += 1
            self.cond.notify()

    def _on_alive(self, sample: Any) -> None:
        rid = self.keys.robot_of(str(sample.key_expr))
        if rid is None:
            return
        with self.lock:
            if sample.kind == self._zenoh.SampleKind.PUT:
                self.alive.add(rid)
                self.alive_since.setdefault(rid, time.monotonic())
            else:
                self.alive.discard(rid)
                self.alive_since.pop(rid, None)

    def _on_root(self, sample: Any) -> None:
        boot = self._root_boot(str(sample.key_expr))
        if boot is None:
            return
        with self.lock:
            (self.roots.add if sample.kind == self._zenoh.SampleKind.PUT else self.roots.discard)(boot)

    def _root_boot(self, key: str) -> int | None:
        head = self.tree.fuser_token(ROOT_NAME) + "/"
        if not key.startswith(head) or not key[len(head):].isdigit():
            return None
        return int(key[len(head):])

    def _on_fused(self, sample: Any) -> None:
        if not self.active:
            data = sample.payload.to_bytes()
            with self.lock:
                self._fused_raw = data

    def _on_fuser(self, sample: Any) -> None:
        g = self.tree.group_of(str(sample.key_expr))
        if g is None or g == ROOT_NAME:
            return
        with self.lock:
            if sample.kind == self._zenoh.SampleKind.PUT:
                self.fusers.add(g)
                self.fusers_seen.add(g)
            else:
                self.fusers.discard(g)

    def _on_query(self, query: Any) -> None:
        with self.lock:
            data = self.current if self.active else None
        if data is not None:
            query.reply(self.keys.fused_map, data)

    def _on_stats(self, query: Any) -> None:
        with self.lock:
            data = self._stats_doc
        query.reply(self.keys.fusion_stats, data, encoding=self._zenoh.Encoding.APPLICATION_JSON)

    def start(self) -> None:
        s = self.session
        lv = s.liveliness()
        root_keys = self.tree.fuser_token(ROOT_NAME) + "/*"
        self._entities.append(lv.declare_token(f"{self.tree.fuser_token(ROOT_NAME)}/{self.boot}"))
        self._entities.append(lv.declare_subscriber(self.keys.all_alive, self._on_alive, history=True))
        self._entities.append(lv.declare_subscriber(self.tree.all_fusers, self._on_fuser, history=True))
        self._entities.append(lv.declare_subscriber(root_keys, self._on_root, history=True))
        self._entities.append(s.declare_subscriber(self.keys.fused_map, self._on_fused))
        self._entities.append(s.declare_subscriber(self.tree.all_groups, self._on_partial))
        # the roots alive now (an older one makes us a standby) before deciding anything
        try:
            for reply in lv.get(root_keys, timeout=2.0):
                ok = reply.ok
                boot = None if ok is None else self._root_boot(str(ok.key_expr))
                if boot is not None:
                    with self.lock:
                        self.roots.add(boot)
        except self._zenoh.ZError as exc:  # pragma: no cover - the subscriber still works
            self.say(f"liveliness query for roots failed: {exc}")
        with self.lock:
            self.roots.add(self.boot)
        # partials published before we came: ask each group's queryable
        try:
            for reply in s.get(self.tree.all_groups, timeout=2.0):
                ok = reply.ok
                if ok is not None:
                    self._on_partial(ok)
        except self._zenoh.ZError as exc:  # pragma: no cover
            self.say(f"query for partials failed: {exc}")
        self._check_role()
        if not self.active:
            self.say("standby root (an older root is active): taking over when it goes")
        self._update_stats()

    def _check_role(self) -> None:
        """Active when no older root's token is alive (see the module docstring)."""
        with self.lock:
            older = any(b < self.boot for b in self.roots)
        if not older and not self.active:
            self._become_active()
        elif older and self.active:
            self._step_down()

    def _become_active(self) -> None:
        s = self.session
        with self.lock:
            last, self._fused_raw = self._fused_raw, None
        last_v = None
        if last is not None:
            try:
                last_v = int(decode_message(last).seq)
            except ValueError:
                last_v = None
        if last_v is not None and last_v >= self.state.version:
            # serve the old root's last map at once and continue after its version: our first
            # fold of the partials (made afresh: the same fold) publishes as the next version
            self.state.version = last_v
            self.state.fused, self.state.fused_robots = Wireframe.empty(), ()
            with self.lock:
                self.current = last
        else:
            last_v = None
        self.active = True
        self._active_entities = [
            s.liveliness().declare_token(self.tree.fuser_token(ROOT_NAME)),
            s.declare_queryable(self.keys.fused_map, self._on_query, complete=True),
            s.declare_queryable(self.keys.fusion_stats, self._on_stats, complete=True),
        ]
        if self.roots != {self.boot} or last_v is not None:
            self.takeovers += 1
            after = "-" if last_v is None else last_v
            self.say(f"root {self.boot} takes over as the active root (after v{after})")
        if self.current is not None:
            self._put(self.current)  # the last map (the old root's, or the stored one) at once

    def _step_down(self) -> None:
        for ent in reversed(self._active_entities):
            try:
                ent.undeclare()
            except Exception:
                pass
        self._active_entities = []
        self.active = False
        self.say(f"an older root is active: root {self.boot} steps down to standby")

    def _meta(self) -> dict[str, Any]:
        st = self.state
        with self.lock:
            alive, fusers, seen = set(self.alive), set(self.fusers), set(self.fusers_seen)
        return {
            "stale": sorted(r for r in st.fused_robots if r not in alive),
            "fusers_down": sorted(g for g in st.partials if g in seen and g not in fusers),
            "group_versions": {g: list(p.key) for g, p in sorted(st.partials.items())},
        }

    def poll(self, timeout: float = 0.05) -> None:
        self._check_role()
        if not self.active:  # a standby keeps the latest partial of each group, undecoded
            time.sleep(timeout)
            return
        with self.cond:
            # with partials waiting, a fuse is due once min_interval_s has passed since the last
            due = self.last_fuse + self.min_interval_s - time.monotonic() if self.inbox else timeout
            if due > 0:
                self.cond.wait(min(timeout, due))
            items = self._take_due()
        if items:
            self._fuse(items)
        now = time.monotonic()
        if self.current is not None and now - self.last_put > self.heartbeat_s:
            data = encode_message(self.state.fused_message(self.stamp_ns, self._meta()))
            with self.lock:
                self.current = data
            self._put(data)
        if now - self._saved_at >= 1.0:
            doc = self.stats_doc()  # once for both (its latency percentiles are fresh)
            self._save(doc, wait=False)
            self._update_stats(doc)

    def _take_due(self) -> dict[str, tuple[bytes, int]]:
        """The inbox, emptied, once ``min_interval_s`` has passed since the last fuse (the lock
        held); nothing before."""
        if not self.inbox or time.monotonic() - self.last_fuse < self.min_interval_s:
            return {}
        items, self.inbox = self.inbox, {}
        return items

    def _fuse(self, items: dict[str, tuple[bytes, int]]) -> None:
        """Offer the partials taken (the newest of each group) and fuse once if any is new."""
        changed = False
        for g, (data, arrived) in items.items():
            try:
                msg = decode_message(data)
            except ValueError:
                continue
            if self.state.offer(g, msg):
                changed = True
                self.transport_ms.extend([max(0.0, (arrived - msg.stamp_ns) / 1e6)])
        if not changed:
            return
        self.last_fuse = time.monotonic()
        if self.state.fuse():
            self._publish()
        else:
            self.state.take_latencies(time.time_ns())  # nothing new to show: not a publish

    def _put(self, data: bytes) -> None:
        self.session.put(self.keys.fused_map, data, congestion_control=self._zenoh.CongestionControl.BLOCK)
        self.last_put = time.monotonic()

    def _publish(self) -> None:
        self.stamp_ns = time.time_ns()
        data = encode_message(self.state.fused_message(self.stamp_ns, self._meta()))
        with self.lock:
            self.current = data
        self._put(data)
        pub = time.time_ns()
        e2e, lvl = self.state.take_latencies(pub)
        self.latency.extend(e2e, pub)
        self.root_ms.extend(lvl, pub)
        for v in e2e:
            self.lat_total += 1
            self._unsaved.append((self.lat_total, v, pub))
        if self.recorder is not None:
            st = self.state
            self.recorder.log_fused(self._sim_time(), st.fused, st.fused_robots, st.version,
                                    max(e2e) if e2e else None)

    def _sim_time(self) -> float:
        """The latest simulated time the partials carry (``meta["t"]``), 0 if none."""
        ts = [p.message.meta.get("t", 0.0) for p in self.state.partials.values()
              if isinstance(p.message.meta, dict)]
        return max((float(t) for t in ts if isinstance(t, (int, float))), default=0.0)

    def _save(self, doc: dict[str, Any] | None = None, wait: bool = True) -> None:
        """Write the store: at once (``wait``), or handed to the store thread."""
        self._saved_at = time.monotonic()
        if self.store is None:
            return
        rows, self._unsaved = self._unsaved, []
        state = json.dumps(self.stats_doc() if doc is None else doc, indent=1).encode()
        if wait:
            if self._writer is not None:
                self._writer.close()  # what it holds first, in order
                self._writer = None
            write_root_store(self.store, rows, self.current, state)
            return
        if self._writer is None:
            self._writer = StoreWriter(self.say)
        self._writer.submit(_RootStoreJob(self.store, rows, self.current, state, self.state.version))

    def stats_doc(self) -> dict[str, Any]:
        st = self.state
        return {
            "version": st.version,
            "role": "root",
            "exact": st.exact,
            "fused": {"vertices": st.fused.n_vertices, "edges": st.fused.n_edges,
                      "robots": list(st.fused_robots)},
            "groups": {g: {"boot": p.key[0], "version": p.key[1], "robots": list(p.message.robots)}
                       for g, p in sorted(st.partials.items())},
            "latency_total": self.lat_total,
            "stats": {"latency_ms": self.latency.summary(True), "root_ms": self.root_ms.summary(True),
                      "merges": st.merges, "received": self.received},
            "transport_ms": self.transport_ms.summary(True),
            "active": self.active,
            "refused_too_many_robots": dict(self.state.refused),
            "root_boot": self.boot,
            "takeovers": self.takeovers,
            "uncovered": self._uncovered(),
            **self._meta(),
            "rss_kb": rss_kb(),
            "pid": os.getpid(),
            "uptime_s": round(time.monotonic() - self.started, 3),
        }

    def _uncovered(self) -> list[str]:
        """Robots alive for over :data:`UNCOVERED_AFTER_S` that no group's partial includes:
        no group's pattern covers them (a list of ids given to ``--robots``), or none of their
        maps was accepted. Logged when the list changes."""
        now = time.monotonic()
        have = {r for p in self.state.partials.values() for r in p.message.robots}
        with self.lock:
            out = sorted(r for r, t in self.alive_since.items()
                         if now - t > UNCOVERED_AFTER_S and r not in have)
        if out != self.uncovered and self.active:
            self.say(f"robots in no group's partial: {', '.join(out) or 'none'}")
        self.uncovered = out
        return out

    def _update_stats(self, doc: dict[str, Any] | None = None) -> None:
        data = json.dumps(self.stats_doc() if doc is None else doc).encode()
        with self.lock:
            self._stats_doc = data

    def close(self) -> None:
        for ent in reversed([*self._entities, *self._active_entities]):
            try:
                ent.undeclare()
            except Exception:
                pass
        with self.cond:
            items, self.inbox = self.inbox, {}
        if self.active and items:  # partials waiting for their interval: fused, not lost
            try:
                self._fuse(items)
            except Exception as exc:  # the session may be closing: the store still gets the map
                self.say(f"could not publish the last fuse: {exc}")
        self._entities.clear()
        self._active_entities = []
        if self.active:
            self._save()  # (after what the store thread holds)
        elif self._writer is not None:
            self._writer.close()
            self._writer = None
        if self.recorder is not None:
            self.recorder.close()


def serve_root(
    session: Any,
    keys: Any,
    groups: list[str] | None,
    stop: threading.Event,
    threshold: float | None = None,
    heartbeat_s: float = 3.0,
    store: str | None = None,
    log: Callable[[str], None] | None = None,
    reset: bool = False,
    recording: dict[str, Any] | None = None,
    min_interval_s: float = 0.0,
) -> RootService:
    """Run the root fuser on an open session until ``stop`` is set (``recording``: ``rrd``,
    ``serve_viewer``, ``recording_id``, ``world``, as ``wiremap fuse``'s flags; ``min_interval_s``:
    fuse at most this often, as ``--min-interval``)."""
    svc = RootService(session, keys, groups, threshold, heartbeat_s, store, log, reset, recording,
                      min_interval_s)
    try:
        svc.start()
        freeze_heap()
        svc.say(f"root fuser ready (groups {'*' if groups is None else ','.join(groups)})")
        while not stop.is_set():
            svc.poll(0.05)
    finally:
        svc.close()
    return svc
