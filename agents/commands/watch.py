"""``wiremap watch [--connect ...] [--save DIR] [--count N] [--timeout S]``.

Subscribes to the fleet's fused map (``wiremap/<fleet>/fused/map``), asks the fusion service's
queryable on the same key once at start for the current map, and prints one line per version::

    fused v12: 148 vertices, 150 edges, 1,234 bytes; 3 robots alive (r1 r2 r3); from r1 r2 r3

"robots alive" counts the liveliness tokens ``wiremap/<fleet>/alive/*`` (subscribed with
history, declared before anything else, so the count is normally complete by the first map);
"from" lists the robots that contributed to the map, with ``stale`` ones (alive no longer)
marked when the fusion service says so.

Every 2 s it also asks ``fused/stats`` and prints a line when the store's health or the
quarantine changes: ``store ok; quarantined 0``, or ``store FAILING (<error>; on disk v41, 7
behind); quarantined 3 (r3: fleet_walls x3)`` (maps kept aside as inconsistent, see ``ARCHITECTURE.md``).

A version is shown once: the query's answer and the subscription may both deliver it, and
copies with the same sender, version and stamp are dropped. A payload that does not decode (or
is not a fused map) is counted, reported on stderr and skipped.

"robots alive" are the robots whose token is alive and that the fusion service does not list as
stale in that map.

``--save DIR`` keeps ``DIR/latest.geojson`` (the message's metadata in the collection's
``properties``, the schema of ``wiremap run``'s ``fused.geojson``) and ``DIR/latest.png`` (the
picture every command draws) up to date, rewritten at most once a second and once more at exit,
and keeps a numbered copy ``DIR/fused-v<version>.geojson`` + ``.png`` at most every
``--save-every S`` seconds (default 30; 0: latest only), so a long watch stays small. Every
file is written atomically.

Stopping: after ``--count N`` versions (exit 0); at ``--timeout S`` seconds (exit 0, or 1 when
fewer than ``--count`` versions came); on SIGINT/SIGTERM (exit 0). The session is always closed.
While no router answers, the command waits for one (bounded by ``--timeout``).
"""

from __future__ import annotations

import argparse
import math
import queue
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

from agents import argtypes
from agents.errors import UserError
from agents.fleet.bus import StopFlag, add_bus_arguments, config_from_args, fleet_keys, open_session

HELP = "subscribe to the fused map and show each version"

#: Seconds the start-up query waits for the fusion service's answer.
QUERY_TIMEOUT = 5.0
HEALTH_EVERY_S = 2.0  # fused/stats asked this often for the store flag and quarantines


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_bus_arguments(parser)
    parser.add_argument(
        "--save", metavar="DIR",
        help="keep DIR/latest.geojson and DIR/latest.png up to date (at most once a second)"
    )
    parser.add_argument(
        "--save-every",
        type=float,
        default=30.0,
        metavar="S",
        help="with --save, also keep a numbered copy fused-v<N> at most every S seconds (default 30; 0: latest only)",  # noqa: E501
    )
    parser.add_argument("--count", type=argtypes.positive_int, metavar="N", help="exit after N versions")
    parser.add_argument(
        "--timeout",
        type=argtypes.positive_float,
        metavar="S",
        help="exit after S seconds (status 1 if --count is not reached)",
    )


def _eprint(text: str) -> None:
    print(f"wiremap watch: {text}", file=sys.stderr, flush=True)


class Watcher:
    """The state of one watch: robots alive, versions seen, counters, and what each payload
    becomes (a line, files). Thread-safe where zenoh callbacks touch it (:meth:`liveliness`)."""

    #: Seconds between two writes of ``latest.*``.
    LATEST_EVERY = 1.0

    def __init__(self, keys: Any, save_dir: Path | None, save_every: float = 30.0) -> None:
        self.keys = keys
        self.save_dir = save_dir
        self.save_every = save_every
        self._pending: tuple[Any, int] | None = None
        self._latest_at = -math.inf
        self._numbered_at = -math.inf
        self.alive: set[str] = set()
        self._lock = threading.Lock()
        self.shown = 0
        self.malformed = 0
        self._seen: deque[tuple[str, int, int]] = deque(maxlen=64)
        self._health: str | None = None

    # zenoh thread
    def liveliness(self, sample: Any) -> None:
        import zenoh

        rid = self.keys.robot_of(str(sample.key_expr))
        if rid is None:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self.alive.discard(rid)
            else:
                self.alive.add(rid)

    def alive_now(self) -> list[str]:
        with self._lock:
            return sorted(self.alive)

    # main thread
    def handle(self, data: bytes) -> str | None:
        """Decode one payload; return the line shown, or None (duplicate or malformed)."""
        from agents.fleet import validate

        try:
            msg = validate.fused_map(data)  # every field checked (agents.fleet.validate)
        except validate.Invalid as exc:
            self.malformed += 1
            if exc.reason == "kind":
                _eprint(f"skipped a {exc.detail}")
            else:
                _eprint(f"skipped a malformed payload ({len(data)} bytes): {exc.detail}")
            return None
        ident = (msg.sender, int(msg.seq), int(msg.stamp_ns))
        if ident in self._seen:
            return None
        self._seen.append(ident)
        self.shown += 1
        line = self.describe(msg, len(data))
        print(line, flush=True)
        if self.save_dir is not None:
            self._pending = (msg, len(data))
            self.flush()
        return line

    def flush(self, force: bool = False) -> None:
        """Save the newest version not saved yet: ``latest.*`` at most every
        :attr:`LATEST_EVERY` seconds (``force``: now), a numbered copy at most every
        ``save_every`` seconds."""
        if self._pending is None:
            return
        now = time.monotonic()
        if not force and now - self._latest_at < self.LATEST_EVERY:
            return
        msg, nbytes = self._pending
        self._pending = None
        self._latest_at = now
        numbered = self.save_every > 0 and now - self._numbered_at >= self.save_every
        if numbered:
            self._numbered_at = now
        self.save(msg, nbytes, numbered)

    def describe(self, msg: Any, nbytes: int) -> str:
        wf = msg.wireframe
        stale = set(_stale(msg))
        alive = [r for r in self.alive_now() if r not in stale]  # the fusion service's word wins
        contributors = " ".join(f"{r}(stale)" if r in stale else r for r in msg.robots) or "-"
        return (
            f"fused v{msg.seq}: {wf.n_vertices} vertices, {wf.n_edges} edges, {nbytes:,} bytes; "
            f"{len(alive)} robot{'' if len(alive) == 1 else 's'} alive"
            f"{' (' + ' '.join(alive) + ')' if alive else ''}; from {contributors}{_frames(msg)}"
        )

    def health(self, data: bytes) -> str | None:
        """A ``fused/stats`` reply: a line when the store's health or the quarantine changed
        since the last one shown (printed), else None."""
        from agents.fleet import validate

        try:
            doc = validate.stats_doc(data)
        except validate.Invalid:
            return None
        line = health_line(doc)
        if line == self._health:
            return None
        self._health = line
        print(line, flush=True)
        return line

    def save(self, msg: Any, nbytes: int, numbered: bool = True) -> None:
        from agents.files.export import message_properties, wireframe_geojson
        from agents.files.io import write_atomic, write_json
        from agents.files.render import map_figure

        assert self.save_dir is not None
        props = message_properties(msg)
        props["bytes"] = int(nbytes)
        stale = set(_stale(msg))
        props["robots_alive"] = [r for r in self.alive_now() if r not in stale]
        doc = wireframe_geojson(msg.wireframe, props)
        title = f"fused map v{msg.seq} from {', '.join(msg.robots) or 'no robot'}"
        png = map_figure(msg.wireframe, title=title)
        try:
            for stem in [self.save_dir / "latest",
                         *([self.save_dir / f"fused-v{msg.seq}"] if numbered else [])]:
                write_json(stem.with_suffix(".geojson"), doc)
                write_atomic(stem.with_suffix(".png"), png)
        except OSError as exc:
            raise UserError(f"cannot save into {self.save_dir}: {exc.strerror or exc}") from None


def _frames(msg: Any) -> str:
    """Robots of unknown start pose (the fused map's ``meta["frames"]``): the frame, the
    islands and the registrations since the last version, with their scores."""
    fr = msg.meta.get("frames") if isinstance(msg.meta, dict) else None
    if not isinstance(fr, dict):
        return ""
    islands = fr.get("islands") or {}
    text = f"; frame of {fr.get('fleet_root')}; islands {' '.join('+'.join(m) for m in islands.values()) or 'none'}"  # noqa: E501
    for r in fr.get("registrations") or []:
        if isinstance(r, dict):
            what = "accepted" if r.get("accepted") else f"refused ({r.get('reason')})"
            text += (
                f"\n  registration {'+'.join(r.get('b_members', []))} -> {'+'.join(r.get('a_members', []))}: "
                f"{what}, confidence {r.get('confidence')}, support {r.get('support_m')} m"
            )
    return text


def health_line(doc: dict[str, Any]) -> str:
    """``store ok|FAILING ...; quarantined N (robot: reason xK, ...)`` from ``fused/stats``."""
    from agents.fleet.validate import get_int

    store: dict[str, Any] = doc["store"] if isinstance(doc.get("store"), dict) else {}
    if store.get("enabled") is False:
        text = "store off"
    elif store.get("ok") is False:
        err = str(store.get("error", ""))[:120]
        text = f"store FAILING ({err}; on disk v{get_int(store, 'written_version')}, {get_int(store, 'behind')} behind)"  # noqa: E501
    else:
        text = "store ok"
    stats: dict[str, Any] = doc["stats"] if isinstance(doc.get("stats"), dict) else {}
    q: dict[str, Any] = doc["quarantine"] if isinstance(doc.get("quarantine"), dict) else {}
    parts = [
        f"{str(r)[:40]}: {str(v.get('reason'))[:40]} x{get_int(v, 'count')}"
        for r, v in list(q.items())[:8] if isinstance(v, dict)
    ]  # fmt: skip
    text += f"; quarantined {get_int(stats, 'quarantined')}"
    return text + (f" ({', '.join(parts)})" if parts else "")


def _stale(msg: Any) -> list[str]:
    stale = msg.meta.get("stale") if isinstance(msg.meta, dict) else None
    return [str(s) for s in stale] if isinstance(stale, (list, tuple)) else []


def run(args: argparse.Namespace) -> int:
    keys = fleet_keys(args)
    cfg = config_from_args(args, "client")
    save_dir: Path | None = None
    if not (math.isfinite(args.save_every) and args.save_every >= 0):
        raise UserError(f"--save-every must be a number of seconds >= 0, got {args.save_every}")
    if args.save:
        from agents.files.io import check_output_dir

        save_dir = check_output_dir("--save", args.save)
        try:
            save_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"--save {save_dir}: cannot create it: {exc.strerror or exc}") from None
    t0 = time.monotonic()
    deadline = None if args.timeout is None else t0 + args.timeout
    watcher = Watcher(keys, save_dir, args.save_every)
    inbox: queue.Queue[bytes] = queue.Queue()
    timed_out = False

    with StopFlag() as stop:
        session = open_session(
            cfg,
            stop.event,
            timeout=args.timeout,
            on_wait=lambda text: _eprint(f"waiting for a router ({text})"),
        )
        if session is None:  # stopped while waiting for the router
            return 0
        try:
            session.liveliness().declare_subscriber(keys.all_alive, watcher.liveliness, history=True)
            session.declare_subscriber(keys.fused_map, lambda s: inbox.put(s.payload.to_bytes()))

            def on_reply(reply: Any) -> None:
                sample = reply.ok
                if sample is not None:
                    inbox.put(sample.payload.to_bytes())

            session.get(keys.fused_map, on_reply, timeout=QUERY_TIMEOUT)
            _eprint(f"watching {keys.fused_map}")
            health: queue.Queue[bytes] = queue.Queue()
            last_health = -math.inf

            def on_stats(reply: Any) -> None:
                if reply.ok is not None:
                    health.put(reply.ok.payload.to_bytes())

            while not stop.is_set():
                if time.monotonic() - last_health >= HEALTH_EVERY_S:  # the store flag and quarantines
                    last_health = time.monotonic()
                    session.get(keys.fusion_stats, on_stats, timeout=QUERY_TIMEOUT)
                while not health.empty():
                    watcher.health(health.get())
                if args.count is not None and watcher.shown >= args.count:
                    break
                wait = 0.2
                if deadline is not None:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        timed_out = True
                        break
                    wait = min(wait, left)
                try:
                    data = inbox.get(timeout=wait)
                except queue.Empty:
                    watcher.flush()
                    continue
                watcher.handle(data)
        finally:
            session.close()
            watcher.flush(force=True)

    _eprint(
        f"{watcher.shown} version{'' if watcher.shown == 1 else 's'} shown, "
        f"{watcher.malformed} malformed payload{'' if watcher.malformed == 1 else 's'} skipped"
    )
    if timed_out and args.count is not None and watcher.shown < args.count:
        _eprint(f"timed out after {args.timeout:g} s with {watcher.shown} of {args.count} versions")
        return 1
    return 0
