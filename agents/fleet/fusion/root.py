"""The root fuser (``wiremap fuse --of-groups NAME,NAME|*``): merges the regional fusers'
partial maps (``wiremap/<fleet>/groups/<NAME>/map``) into the fleet's fused map.

* subscribes to the partials (each group's newest by ``(meta.boot, version)``, so a restarted
  or taken-over group supersedes the old one whatever its version), to the robots' liveliness
  tokens (the stale list, as the one-process service) and to the fusers' tokens
  (``fusers/<NAME>``: a group whose fuser is gone keeps its last partial in the map, listed in
  ``meta.fusers_down``, until a takeover or a restart publishes again);
* publishes ``wiremap/<fleet>/fused/map`` (:class:`RootState`: the one-process fold when the
  groups are the fold's subtrees, ``meta.exact``), on every change and every ``heartbeat_s``,
  answers queries for it and for its counters (``fused/stats``: versions, per-level latency,
  the groups' versions);
* latency: ``latency_ms`` from each robot map's publish (the stamps a partial carries) to the
  fused publish that includes it (end to end, the figure of the one-process service);
  ``root_ms`` from a partial's publish to that fused publish (the root's level); with
  ``--store DIR`` the end-to-end samples go to ``DIR/latency.log`` and the map to
  ``DIR/fused.wfm`` and ``DIR/state.json`` (as the one-process store's views).
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from agents.fleet.fusion.codec import decode_message, encode_message
from agents.fleet.fusion.stats import LatencyWindow
from agents.fleet.fusion.store import append_latency_log
from agents.fleet.fusion.tree import GroupKeys, RootState
from agents.fleet.proc import freeze_heap, rss_kb

ROOT_NAME = "root"


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


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
    ) -> None:
        import zenoh

        self._zenoh = zenoh
        self.session = session
        self.keys = keys
        self.tree = GroupKeys(keys.prefix)
        self.groups = set(groups) if groups else None
        self.state = RootState(threshold)
        self.heartbeat_s = heartbeat_s
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
        self._stats_doc = b"{}"
        self._entities: list[Any] = []
        self.received = 0
        self.started = time.monotonic()

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
            (self.alive.add if sample.kind == self._zenoh.SampleKind.PUT else self.alive.discard)(rid)

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
            data = self.current
        if data is not None:
            query.reply(self.keys.fused_map, data)

    def _on_stats(self, query: Any) -> None:
        with self.lock:
            data = self._stats_doc
        query.reply(self.keys.fusion_stats, data, encoding=self._zenoh.Encoding.APPLICATION_JSON)

    def start(self) -> None:
        s = self.session
        self._entities.append(s.liveliness().declare_token(self.tree.fuser_token(ROOT_NAME)))
        self._entities.append(
            s.liveliness().declare_subscriber(self.keys.all_alive, self._on_alive, history=True)
        )
        self._entities.append(
            s.liveliness().declare_subscriber(self.tree.all_fusers, self._on_fuser, history=True)
        )
        self._entities.append(s.declare_queryable(self.keys.fused_map, self._on_query, complete=True))
        self._entities.append(s.declare_queryable(self.keys.fusion_stats, self._on_stats, complete=True))
        self._entities.append(s.declare_subscriber(self.tree.all_groups, self._on_partial))
        # partials published before we came: ask each group's queryable
        try:
            for reply in s.get(self.tree.all_groups, timeout=2.0):
                ok = reply.ok
                if ok is not None:
                    self._on_partial(ok)
        except self._zenoh.ZError as exc:  # pragma: no cover
            self.say(f"query for partials failed: {exc}")
        self._update_stats()

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
        with self.cond:
            if not self.inbox:
                self.cond.wait(timeout)
            items, self.inbox = self.inbox, {}
        changed = False
        for g, (data, arrived) in items.items():
            try:
                msg = decode_message(data)
            except ValueError:
                continue
            if self.state.offer(g, msg):
                changed = True
                self.transport_ms.extend([max(0.0, (arrived - msg.stamp_ns) / 1e6)])
        if changed and self.state.fuse():
            self._publish()
        elif changed:
            self.state.take_latencies(time.time_ns())  # nothing new to show: not a publish
        now = time.monotonic()
        if self.current is not None and now - self.last_put > self.heartbeat_s:
            data = encode_message(self.state.fused_message(self.stamp_ns, self._meta()))
            with self.lock:
                self.current = data
            self._put(data)
        if now - self._saved_at >= 1.0:
            self._save()
            self._update_stats()

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

    def _save(self) -> None:
        self._saved_at = time.monotonic()
        if self.store is None:
            return
        self.store.mkdir(parents=True, exist_ok=True)
        if self._unsaved:
            append_latency_log(self.store, self._unsaved)
            self._unsaved = []
        if self.current is not None:
            _atomic_write(self.store / "fused.wfm", self.current)
        _atomic_write(self.store / "state.json", json.dumps(self.stats_doc(), indent=1).encode())

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
            **self._meta(),
            "rss_kb": rss_kb(),
            "pid": os.getpid(),
            "uptime_s": round(time.monotonic() - self.started, 3),
        }

    def _update_stats(self) -> None:
        data = json.dumps(self.stats_doc()).encode()
        with self.lock:
            self._stats_doc = data

    def close(self) -> None:
        for ent in reversed(self._entities):
            try:
                ent.undeclare()
            except Exception:
                pass
        self._entities.clear()
        self._save()


def serve_root(
    session: Any,
    keys: Any,
    groups: list[str] | None,
    stop: threading.Event,
    threshold: float | None = None,
    heartbeat_s: float = 3.0,
    store: str | None = None,
    log: Callable[[str], None] | None = None,
) -> RootService:
    """Run the root fuser on an open session until ``stop`` is set."""
    svc = RootService(session, keys, groups, threshold, heartbeat_s, store, log)
    try:
        svc.start()
        freeze_heap()
        svc.say(f"root fuser ready (groups {'*' if groups is None else ','.join(groups)})")
        while not stop.is_set():
            svc.poll(0.05)
    finally:
        svc.close()
    return svc
