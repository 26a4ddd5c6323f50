"""A regional fuser (``wiremap fuse --group NAME --robots PATTERN``): the fusion service over a
group of robots, publishing its partial map for the root (:mod:`agents.fleet.fusion.root`).

It is a :class:`~agents.fleet.fusion.service.FusionService` with other keys:

* it takes the maps of the robots its :class:`~agents.fleet.fusion.tree.RobotSelector` matches
  (a subscription narrowed to the pattern where Zenoh can express it, filtered in the callback
  otherwise; other robots' maps are not decoded);
* it publishes a ``FUSED_MAP`` on ``wiremap/<fleet>/groups/<NAME>/map`` (and answers queries for
  it; counters on ``groups/<NAME>/stats``): the fold of its robots, frontiers *not* closed (a
  node of the fleet's fold tree; the root closes them), ``robots`` its sorted ids (bit ``j`` of
  the sources is ``robots[j]``), ``meta = {version, threshold, group, boot (process start, ns:
  orders restarts and takeovers), select (its pattern), stamps (the publish stamps of the robot
  maps this version newly includes: the root's end-to-end latency), stale, t}``;
* it declares the liveliness token ``wiremap/<fleet>/fusers/<NAME>``;
* alignment prefix: it subscribes to the other groups' partials and aligns its robots onto the
  fold of the robots before its group (:meth:`RootState.prefix_before`: the tree's nodes over
  ``[0, lo)`` made from those partials; ``FusionState.base``), so its first robot is not an
  anchor unless its group comes first, as in one process;
* standby (:class:`Standby`): it keeps the latest raw map of every robot of the other groups
  (bytes only, nothing decoded), and when a group's fuser token disappears and it is that
  group's designated standby (the next live fuser name after it, cyclically), it starts a
  second service for that group in this process, fed at once from those bytes, publishing on
  the group's key with a newer ``boot``; when the group's own fuser is back (its token), the
  takeover retires (the restarted fuser publishes with a newer boot still, so the root switches
  back on its first partial).

  *The standby's cost (the choice made here)*: a hot standby of **bytes**, not of maps. While
  the group's fuser lives, the standby decodes and merges nothing of that group: per map it
  pays one Zenoh callback and a copy of the payload into a dict (the latest per robot). What
  it saves: a takeover publishes from every robot's latest map at once (0.24 s gap at 64
  robots, ``bench fleet --kill-fuser``) instead of waiting up to a heartbeat (2 s) for each
  robot to re-send. Measured (``python -m tests.standby_cost``, 64 robots x 10 Hz, a fuser
  over half of them, ``docs/experiments.md``): 0.111 core with the standby against 0.106 with
  ``--no-standby``, +0.005 core. What it does cost: a group pattern Zenoh can express (one
  glob ``PREFIX*``) would subscribe to its robots only; the standby subscribes to every
  robot's map, so every robot's bytes reach every regional fuser (across sites, over the
  link: there use ``--no-standby``). Range, hash and list patterns subscribe to every robot
  anyway (filtered in the callback), so for them the standby adds no traffic.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from typing import Any

from agents.fleet.fusion.codec import decode_message, encode_message
from agents.fleet.fusion.service import FusionService, ServeOptions
from agents.fleet.fusion.tree import GroupKeys, RobotSelector, RootState
from agents.fleet.proc import freeze_heap
from wire_codec.message import MessageKind

ROOT_NAME = "root"


class GroupView:
    """The keys a :class:`FusionService` uses, for a regional fuser: its partial map in place
    of the fused map, its robots' maps only."""

    def __init__(self, keys: Any, group: str, selector: RobotSelector) -> None:
        self.fleet = keys
        self.prefix = keys.prefix
        self.group = group
        self.selector = selector
        self.tree = GroupKeys(keys.prefix)
        self.fused_map = self.tree.group_map(group)
        self.fusion_stats = self.tree.group_stats(group)
        self.all_maps = f"{keys.prefix}/robots/{selector.key_chunk()}/map"
        self.all_poses = keys.all_poses
        self.all_viz = keys.all_viz
        self.all_alive = keys.all_alive

    def robot_of(self, key: str) -> str | None:
        return self.fleet.robot_of(key)


class RegionalService(FusionService):
    """A regional fuser (see the module docstring)."""

    def __init__(
        self,
        session: Any,
        keys: Any,
        opts: ServeOptions,
        group: str,
        selector: RobotSelector,
        log: Callable[[str], None] | None = None,
        token: bool = True,
        seed: dict[str, bytes] | None = None,
    ) -> None:
        # before the service's own set-up: a resumed store publishes with _meta() at once
        self.group = group
        self.selector = selector
        self.fleet_keys = keys
        self.tree = GroupKeys(keys.prefix)
        self.boot = time.time_ns()
        super().__init__(session, GroupView(keys, group, selector), opts, log)
        self.state.sender = group
        self.others = RootState(opts.config.threshold)
        self._others_raw: dict[str, bytes] = {}
        self._own_raw: bytes | None = None
        self._sent: collections.deque[bytes] = collections.deque(maxlen=8)  # our latest puts
        self._decoded_at: dict[str, float] = {}
        self._base_ident: Any = None
        self._token = token
        self._seed = seed or {}
        self.standby: Standby | None = None
        if self.recorder is not None:
            # the recording of a tree is one per fuser, merged (wiremap run): this fuser draws
            # its own robots (maps in the fleet frame, poses, scans) and its partial map; the
            # root draws the fused map
            self.recorder.fused_path = f"groups/{group}"

    # zenoh threads
    def _on_map(self, sample: Any) -> None:
        key = str(sample.key_expr)
        rid = self.fleet_keys.robot_of(key)
        if rid is None or not self.selector.matches(rid):
            if self.standby is not None and rid is not None:
                self.standby.keep(key, sample.payload)
            return
        super()._on_map(sample)

    def _on_pose(self, sample: Any) -> None:
        rid = self.fleet_keys.robot_of(str(sample.key_expr))
        if rid is not None and self.selector.matches(rid):
            super()._on_pose(sample)

    def _on_viz(self, sample: Any) -> None:
        rid = self.fleet_keys.robot_of(str(sample.key_expr))
        if rid is not None and self.selector.matches(rid):
            super()._on_viz(sample)

    def _on_partial(self, sample: Any) -> None:
        g = self.tree.group_of(str(sample.key_expr))
        if g is None:
            return
        if g == self.group:
            if self._token:  # the owner: is someone else publishing our group (a takeover)?
                data = sample.payload.to_bytes()
                with self.lock:
                    if data not in self._sent:
                        self._own_raw = data
            return
        with self.lock:
            self._others_raw[g] = sample.payload.to_bytes()

    def start(self) -> None:
        s = self.session
        if self._token:
            self._entities.append(s.liveliness().declare_token(self.tree.fuser_token(self.group)))
        if self.opts.config.refine or self.standby is not None or self._token:
            self._entities.append(s.declare_subscriber(self.tree.all_groups, self._on_partial))
        if self.standby is not None and self.keys.all_maps != self.fleet_keys.all_maps:
            # the standby needs every robot's bytes: one subscription for all, filtered in _on_map
            self.keys.all_maps = self.fleet_keys.all_maps
        super().start()
        for key, raw in self._seed.items():
            self.intake.put(key, raw)

    def _put(self, data: bytes) -> None:
        with self.lock:
            self._sent.append(data)
        super()._put(data)

    def _meta(self) -> dict[str, Any]:
        m = super()._meta()
        m.update({"group": self.group, "boot": self.boot, "select": self.selector.text,
                  "stamps": self.state.pending_stamps()})
        return m

    def poll(self, timeout: float = 0.05) -> None:
        self._update_base()
        super().poll(timeout)

    def _check_takeover(self) -> None:
        """A partial of our group with a newer boot than ours comes from a takeover that started
        while we were cut off (our token lost, we alive): take a newer boot ourselves and
        re-publish, so that the root follows us again (the takeover retires when it sees our
        token)."""
        with self.lock:
            raw, self._own_raw = self._own_raw, None
        if raw is None:
            return
        try:
            msg = decode_message(raw)
        except ValueError:
            return
        meta = msg.meta if isinstance(msg.meta, dict) else {}
        boot = meta.get("boot")
        if isinstance(boot, int) and boot > self.boot:
            self.boot = time.time_ns()
            self.say(f"another fuser published group {self.group} (boot {boot}): taking it back")
            if self.current is not None:
                data = encode_message(self.state.fused_message(self.version_stamp_ns, self._meta()))
                with self.lock:
                    self.current = data
                self._put(data)

    def _update_base(self) -> None:
        """Take the other groups' new partials; the alignment prefix follows them."""
        self._check_takeover()
        with self.lock:
            raws, self._others_raw = self._others_raw, {}
        if not raws:
            return
        now = time.monotonic()
        first = min(self.state.robots, default=None)
        for g, raw in raws.items():
            # a group whose robots all come after ours is no part of our prefix: its partials
            # are decoded every 2 s only (the standby's view of its pattern)
            known = self.others.partials.get(g)
            if (known is not None and first is not None and min(known.message.robots, default="") > first
                    and now - self._decoded_at.get(g, -1e9) < 2.0):
                continue
            self._decoded_at[g] = now
            try:
                msg = decode_message(raw)
            except ValueError:
                continue
            if msg.kind == MessageKind.FUSED_MAP:
                self.others.offer(g, msg)
                if self.standby is not None:
                    self.standby.learn(g, msg)
        if not self.opts.config.refine or not self.state.robots:
            return
        base = self.others.prefix_before(sorted(self.state.robots))
        ident = None if base is None else base[0]
        if ident != self._base_ident:
            self._base_ident = ident
            self.state.base = base
            # the alignments' prefix moved: a fuse marks them stale, and once quiet the full
            # path re-aligns onto it (as a change of the robots before them would in one process)
            self.refuse = True
            self.last_change = time.monotonic()

    def retire(self) -> None:
        """Undeclare everything without a final fuse (a takeover that is no longer needed)."""
        for ent in reversed(self._entities):
            try:
                ent.undeclare()
            except Exception:  # already undeclared or session closed
                pass
        self._entities.clear()
        if self.writer is not None:
            self.writer.close()


class Standby:
    """Hot standby of a regional fuser for the other groups (see the module docstring)."""

    def __init__(self, owner: RegionalService, opts: ServeOptions, log: Callable[[str], None]) -> None:
        self.owner = owner
        self.opts = opts
        self.say = log
        self.lock = threading.Lock()
        self.raw: dict[str, Any] = {}  # robot map key -> latest payload (bytes)
        self.selects: dict[str, str] = {}  # group -> its pattern (from its partials)
        self.alive: set[str] = set()
        self.seen: set[str] = set()
        self.takeovers: dict[str, RegionalService] = {}
        self._events: list[tuple[str, bool]] = []
        self.dead: dict[str, float] = {}  # groups gone whose takeover waits for their pattern

    def keep(self, key: str, payload: Any) -> None:
        data = payload.to_bytes() if hasattr(payload, "to_bytes") else bytes(payload)
        with self.lock:
            self.raw[key] = data

    def learn(self, group: str, msg: Any) -> None:
        meta = msg.meta if isinstance(msg.meta, dict) else {}
        sel = meta.get("select")
        if isinstance(sel, str) and group not in self.takeovers:
            self.selects[group] = sel

    def on_token(self, sample: Any) -> None:
        g = self.owner.tree.group_of(str(sample.key_expr))
        if g is None or g == ROOT_NAME:
            return
        import zenoh

        with self.lock:
            self._events.append((g, sample.kind == zenoh.SampleKind.PUT))

    def designated(self, dead: str) -> bool:
        """Whether this fuser takes ``dead``'s robots: the first live fuser name after it in
        sorted order (cyclically), this one included."""
        names = sorted((self.alive | {self.owner.group}) - {dead})
        after = [n for n in names if n > dead]
        return (after or names)[0] == self.owner.group if names else False

    def step(self) -> None:
        with self.lock:
            events, self._events = self._events, []
        if events:
            self.owner._update_base()  # partials that came with the news: learn their patterns first
        for g, up in events:
            if g == self.owner.group:
                continue
            if up:
                self.alive.add(g)
                self.seen.add(g)
                t = self.takeovers.pop(g, None)
                if t is not None:
                    t.retire()
                    self.say(f"fuser {g} is back: takeover retired")
            else:
                self.alive.discard(g)
                if g not in self.takeovers:
                    self.dead[g] = time.monotonic()
        for g, since in list(self.dead.items()):
            if g in self.alive or g in self.takeovers:
                del self.dead[g]
            elif not self.designated(g):
                del self.dead[g]
            elif g in self.selects:
                del self.dead[g]
                self._take_over(g)
            elif time.monotonic() - since > 5.0:
                del self.dead[g]
                self.say(f"fuser {g} is gone and none of its partials told its robots: no takeover")
        for t in self.takeovers.values():
            t.poll(0.0)

    def _take_over(self, g: str) -> None:
        sel = RobotSelector.parse(self.selects[g])
        with self.lock:
            seed = {
                k: v
                for k, v in self.raw.items()
                if (r := self.owner.fleet_keys.robot_of(k)) and sel.matches(r)
            }
        opts = ServeOptions(
            heartbeat_s=self.opts.heartbeat_s, min_interval_s=self.opts.min_interval_s,
            config=self.opts.config,
            limits=self.opts.limits, full_after_s=self.opts.full_after_s, align_wait_s=self.opts.align_wait_s,
        )
        t = RegionalService(self.owner.session, self.owner.fleet_keys, opts, g, sel,
                            lambda s: self.say(f"[takeover {g}] {s}"), token=False, seed=seed)
        t.start()
        self.takeovers[g] = t
        self.say(f"fuser {g} is gone: taking over its robots ({sel.text}, {len(seed)} maps at hand)")

    def close(self) -> None:
        for t in self.takeovers.values():
            t.retire()
        self.takeovers.clear()


def serve_regional(
    session: Any,
    keys: Any,
    opts: ServeOptions,
    group: str,
    selector: RobotSelector,
    stop: threading.Event,
    log: Callable[[str], None] | None = None,
    standby: bool = True,
) -> RegionalService:
    """Run a regional fuser on an open session until ``stop`` is set (see the module
    docstring); returns the service (its state saved when ``opts.store`` is set)."""
    say = log or (lambda _s: None)
    svc = RegionalService(session, keys, opts, group, selector, say)
    tok_sub = None
    if standby:
        svc.standby = Standby(svc, opts, say)
    try:
        svc.start()
        if svc.standby is not None:
            tok_sub = session.liveliness().declare_subscriber(
                svc.tree.all_fusers, svc.standby.on_token, history=True
            )
        freeze_heap()
        svc.say(f"regional fuser {group} ready ({selector.text})")
        while not stop.is_set():
            svc.poll(0.05 if svc.standby is None or not svc.standby.takeovers else 0.02)
            if svc.standby is not None:
                svc.standby.step()
    finally:
        if tok_sub is not None:
            try:
                tok_sub.undeclare()
            except Exception:
                pass
        if svc.standby is not None:
            svc.standby.close()
        svc.close()
    return svc
