"""The fusion service: every robot's latest map -> one fleet map.

Two layers:

* :class:`FusionState`, the pure core (no zenoh, no rerun, no clock of its own): keeps each
  robot's latest :class:`~wire_codec.message.MapMessage`, recomputes the fused map, stores and
  restores itself on disk.
* :func:`serve`, the Zenoh shell: subscribes to ``robots/*/map`` (a FIFO: no map is dropped),
  ``robots/*/pose`` and ``robots/*/viz`` (rings: only the latest matters) and ``alive/*``;
  publishes the fused map on every change and answers queries for it; logs to Rerun.

Order independence, by construction: the fused map is a function of the *set* of latest robot
maps only. A robot's latest map is the one with the greatest ``(meta["boot"], seq, sha256 of its
bytes)``, whatever the order of arrival, and duplicates are no-ops; the fused map is then
recomputed from scratch, visiting robots in sorted-id order. Robot ``k`` of the sorted ids owns
bit ``k`` of ``Wireframe.sources`` (``MapMessage.robots`` lists them), so at most 64 robots.

Fleet frame, in three steps per robot (choices where the paper and the issue are silent):

1. the map (in the robot's odometry frame) is moved by its start pose (``MapMessage.origin``);
2. if ``mapping.icp`` is available and ``FusionConfig.refine`` is on, a wireframe ICP aligns it
   to the fused map of the robots before it (sorted order; the first robot is the anchor).
   The correction is kept only when it is small (``max_refine_m`` / ``max_refine_rad``): the
   start poses are known, ICP only removes residual odometry drift;
3. :func:`mapping.merge.merge` adds it to the fused map with the merge threshold
   ``FusionConfig.threshold`` (default: the largest ``resolution`` among the robot maps).

Finally :func:`close_frontiers` removes frontiers of one robot that another robot's walls
close (see there).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from agents.errors import UserError
from agents.io import write_atomic, write_json
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe
from wire_codec.message import MapMessage, MessageKind

MAX_ROBOTS = 64
DEFAULT_THRESHOLD = 0.2
FUSION_ID = "fusion"


# ---------------------------------------------------------------------- codec access
def _codec() -> tuple[Callable[[MapMessage], bytes], Callable[[bytes], MapMessage], type[Exception]]:
    import wire_codec

    try:
        from wire_codec import CodecError, decode, encode  # type: ignore[attr-defined]
    except ImportError as exc:  # the codec is written by another helper
        raise RuntimeError(f"wire_codec.encode/decode are not available yet: {exc}") from None
    del wire_codec
    return encode, decode, CodecError


def encode_message(msg: MapMessage) -> bytes:
    return _codec()[0](msg)


def decode_message(data: bytes) -> MapMessage:
    """Decode codec bytes; raises ``ValueError`` (``CodecError``) on malformed payloads."""
    return _codec()[1](data)


# ---------------------------------------------------------------------- frontier closing
def close_frontiers(wf: Wireframe, threshold: float, max_angle: float = math.radians(20.0)) -> Wireframe:
    """Remove frontiers that another wall of the fused map closes.

    A frontier vertex ``v`` (where a wall leaves what its robot saw) is *closed* when it lies
    within ``threshold`` of the interior of an edge ``e`` that does not touch it (more than
    ``threshold`` from both of ``e``'s ends): someone saw the wall go on. Then (choices; the
    paper only says such frontiers should disappear):

    * each wall at ``v`` that runs along ``e`` (within ``max_angle``, same direction) is
      covered by ``e``: it is dropped when its other end ``u`` also lies along ``e``;
      otherwise it is re-attached from ``v`` to ``e``'s nearer end, so that the wall stays one
      connected chain (``u`` -> end of ``e``), keeping its likelihood and sources;
    * if walls at an angle to ``e`` remain at ``v``, ``v`` is where that wall meets ``e``: a
      real corner, relabelled ``NOMINAL``;
    * a vertex left without walls is dropped.

    An edge that runs opposite to one of ``v``'s walls is the back of a thin wall and does not
    close ``v``. When several edges close ``v``, the one of lowest index is used. Decisions are made on the
    input map and applied together.
    """
    fr = np.flatnonzero(wf.labels == Label.FRONTIER)
    if len(fr) == 0 or wf.n_edges == 0:
        return wf
    P, E = wf.points, wf.edges
    A = P[E[:, 0]]
    D = P[E[:, 1]] - A
    L = np.hypot(D[:, 0], D[:, 1])
    ok = L > 1e-12
    dirs = np.zeros_like(D)
    dirs[ok] = D[ok] / L[ok, None]
    cos_max = math.cos(max_angle)

    def coords(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc-length along, and distance across, every edge for point p."""
        rel = p - A
        t = rel[:, 0] * dirs[:, 0] + rel[:, 1] * dirs[:, 1]
        d = np.abs(dirs[:, 0] * rel[:, 1] - dirs[:, 1] * rel[:, 0])
        return t, d

    drop_edge = np.zeros(wf.n_edges, dtype=bool)
    edges = E.copy()
    relabel: list[int] = []
    for v in fr.tolist():
        touches = (E[:, 0] == v) | (E[:, 1] == v)
        t, d = coords(P[v])
        closing = np.flatnonzero(ok & ~touches & (d <= threshold) & (t > threshold) & (t < L - threshold))
        if len(closing) == 0:
            continue
        inc = np.flatnonzero(touches)
        # an edge running the other way is the back of a thin wall, not a continuation
        usable = [int(k) for k in closing if not np.any(ok[inc] & (dirs[inc] @ dirs[k] <= -cos_max))]
        if not usable:
            continue
        k = usable[0]
        at_angle = 0
        for j in inc.tolist():
            if not ok[j] or float(dirs[j] @ dirs[k]) < cos_max:
                at_angle += 1
                continue
            end_v = 0 if E[j, 0] == v else 1
            u = int(E[j, 1 - end_v])
            tu = float((P[u] - A[k]) @ dirs[k])
            du = abs(float(dirs[k, 0] * (P[u] - A[k])[1] - dirs[k, 1] * (P[u] - A[k])[0]))
            if du <= threshold and -threshold <= tu <= L[k] + threshold:
                drop_edge[j] = True  # entirely along e: covered
                continue
            w = int(E[k, 0]) if tu < 0 else int(E[k, 1])
            if float(np.hypot(*(P[w] - P[u]))) <= threshold:
                drop_edge[j] = True
            else:
                edges[j, end_v] = w
        if at_angle:
            relabel.append(v)
    if not drop_edge.any() and np.array_equal(edges, E) and not relabel:
        return wf
    labels = wf.labels.copy()
    labels[relabel] = Label.NOMINAL
    keep = ~drop_edge & (edges[:, 0] != edges[:, 1])
    out = Wireframe(P, labels, edges[keep], wf.likelihood[keep], wf.sources[keep])
    return out.compacted()


# ---------------------------------------------------------------------- the pure core
MergeFn = Callable[[Wireframe, Wireframe, float], Wireframe]


def default_merge(base: Wireframe, new: Wireframe, threshold: float) -> Wireframe:
    """:func:`mapping.merge.merge` with ``MergeConfig(threshold=threshold)``."""
    from mapping.merge import MergeConfig, merge

    return merge(base, new, MergeConfig(threshold=threshold))


@dataclass(frozen=True)
class FusionConfig:
    """Fusion parameters.

    threshold : merge threshold in metres; None: the largest ``resolution`` of the robot maps
        (``DEFAULT_THRESHOLD`` when there are none).
    refine : align each robot's map to the rest with ``mapping.icp`` when that module exists.
    max_refine_m, max_refine_rad : largest accepted ICP correction.
    close_frontiers : apply :func:`close_frontiers` to the result.
    """

    threshold: float | None = None
    refine: bool = True
    max_refine_m: float = 0.6
    max_refine_rad: float = math.radians(6.0)
    close_frontiers: bool = True


@dataclass(frozen=True)
class RobotEntry:
    """A robot's latest map as received: the message, its exact bytes, its order key."""

    message: MapMessage
    raw: bytes
    key: tuple[int, int, str]


@dataclass
class FusionStats:
    received: int = 0
    accepted: int = 0
    duplicates: int = 0
    outdated: int = 0
    malformed: int = 0
    rejected: int = 0
    published: int = 0
    latencies_ms: list[float] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        lat = np.asarray(self.latencies_ms, dtype=np.float64)
        return {
            "received": self.received,
            "accepted": self.accepted,
            "duplicates": self.duplicates,
            "outdated": self.outdated,
            "malformed": self.malformed,
            "rejected": self.rejected,
            "published": self.published,
            "latency_ms": latency_summary(lat),
        }


def latency_summary(lat_ms: Iterable[float]) -> dict[str, float | int | None]:
    a = np.asarray(list(lat_ms), dtype=np.float64)
    if len(a) == 0:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    return {
        "n": len(a),
        "p50": float(np.percentile(a, 50)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
    }


def order_key(msg: MapMessage, raw: bytes) -> tuple[int, int, str]:
    """``(boot, seq, sha256)``: a restarted robot (new ``meta["boot"]``) supersedes its old
    maps even though its ``seq`` starts again; the hash breaks (unexpected) ties the same way
    whatever the arrival order."""
    boot = msg.meta.get("boot", 0) if isinstance(msg.meta, dict) else 0
    try:
        boot = int(boot)
    except (TypeError, ValueError):
        boot = 0
    return (boot, int(msg.seq), hashlib.sha256(raw).hexdigest())


class FusionState:
    """The fusion service's state, without any I/O but the store.

    Parameters
    ----------
    config : :class:`FusionConfig`.
    sender : the id in the fused messages' envelope.
    merge_fn : ``merge_fn(base, new, threshold) -> Wireframe``; default
        :func:`mapping.merge.merge` (tests may pass another).
    """

    def __init__(
        self,
        config: FusionConfig | None = None,
        sender: str = FUSION_ID,
        merge_fn: MergeFn | None = None,
    ) -> None:
        self.config = config or FusionConfig()
        self.sender = sender
        self.merge_fn: MergeFn = merge_fn or default_merge
        self.robots: dict[str, RobotEntry] = {}
        self.fused: Wireframe = Wireframe.empty()
        self.fused_robots: tuple[str, ...] = ()
        self.corrections: dict[str, Pose] = {}
        self.version = 0
        self.stats = FusionStats()
        self._pending: dict[str, int] = {}  # robot -> stamp_ns of an accepted map not yet fused
        self._chain: list[tuple[Any, Wireframe, Pose | None]] = []  # compute()'s prefix cache

    # ------------------------------------------------------------------ input
    def offer(self, data: bytes, key_robot: str | None = None) -> bool:
        """Decode and :meth:`add` a payload from ``robots/<key_robot>/map``.

        Returns whether the robot's latest map changed. A malformed payload (``CodecError``),
        a fused map, or a sender that does not match the key is counted and dropped.
        """
        self.stats.received += 1
        try:
            msg = decode_message(bytes(data))
        except ValueError:
            self.stats.malformed += 1
            return False
        if msg.kind != MessageKind.ROBOT_MAP or (key_robot is not None and msg.sender != key_robot):
            self.stats.rejected += 1
            return False
        return self._add(msg, bytes(data))

    def add(self, msg: MapMessage) -> bool:
        """Add a robot map given as a message: it is encoded and decoded first, so that the
        state holds exactly what would have travelled (the codec quantises coordinates)."""
        return self.offer(encode_message(msg), msg.sender)

    def _add(self, msg: MapMessage, raw: bytes) -> bool:
        rid = msg.sender
        key = order_key(msg, raw)
        old = self.robots.get(rid)
        if old is not None:
            if key == old.key:
                self.stats.duplicates += 1
                return False
            if key < old.key:
                self.stats.outdated += 1
                return False
        elif len(self.robots) >= MAX_ROBOTS:
            self.stats.rejected += 1
            return False
        self.robots[rid] = RobotEntry(msg, raw, key)
        self.stats.accepted += 1
        same = old is not None and _same_map(old.message, msg)
        if not same:
            self._pending.setdefault(rid, int(msg.stamp_ns))
        return not same

    # ------------------------------------------------------------------ fusion
    @property
    def threshold(self) -> float:
        if self.config.threshold is not None:
            return float(self.config.threshold)
        res = [float(e.message.resolution) for e in self.robots.values() if e.message.resolution > 0]
        return max(res) if res else DEFAULT_THRESHOLD

    def robot_in_fleet(self, robot: str) -> Wireframe:
        """A robot's latest map in the fleet frame (start pose, then the ICP correction)."""
        m = self.robots[robot].message
        wf = m.wireframe.transformed(m.origin)
        corr = self.corrections.get(robot)
        return wf.transformed(corr) if corr is not None else wf

    def compute(self) -> tuple[Wireframe, tuple[str, ...], dict[str, Pose]]:
        """The fused map of the current latest maps.

        A pure function of the set of latest maps (and the config). The partial results after
        each robot are cached under the keys of the robots so far (a prefix of the sorted ids),
        so when only a late robot's map changed, the prefix before it is reused; this changes
        the cost, never the result.
        """
        ids = tuple(sorted(self.robots))
        thr = self.threshold
        acc = Wireframe.empty()
        corrections: dict[str, Pose] = {}
        chain: list[tuple[Any, Wireframe, Pose | None]] = []
        prefix: tuple[Any, ...] = (thr, self.config)
        cached = self._chain
        for k, rid in enumerate(ids):
            prefix = (*prefix, rid, self.robots[rid].key)
            if k < len(cached) and cached[k][0] == prefix:
                _, acc, corr = cached[k]
                if corr is not None:
                    corrections[rid] = corr
                chain.append(cached[k])
                continue
            cached = []  # the prefix differs from here on
            m = self.robots[rid].message
            wf = m.wireframe.transformed(m.origin)
            wf = wf.replace(sources=np.full(wf.n_edges, np.uint64(1) << np.uint64(k), dtype=np.uint64))
            corr = None
            if self.config.refine and acc.n_edges and wf.n_edges:
                corr = _refine(wf, acc, thr, self.config)
                if corr is not None:
                    corrections[rid] = corr
                    wf = wf.transformed(corr)
            if wf.n_vertices:
                acc = wf if acc.n_vertices == 0 else self.merge_fn(acc, wf, thr)
            chain.append((prefix, acc, corr))
        self._chain = chain
        if self.config.close_frontiers:
            acc = close_frontiers(acc, thr)
        return acc, ids, corrections

    def fuse(self) -> bool:
        """Recompute the fused map; bump ``version`` and return True when it changed."""
        wf, ids, corr = self.compute()
        self.corrections = corr
        changed = ids != self.fused_robots or not wf.almost_equal(self.fused, tol=1e-9)
        if changed:
            self.fused, self.fused_robots = wf, ids
            self.version += 1
        else:
            self._pending.clear()
        return changed

    def take_latencies(self, published_ns: int) -> list[float]:
        """Latency (ms) from each robot map that changed since the last fused publish to this
        publish at ``published_ns`` (same machine clock); recorded in ``stats``."""
        out = [max(0.0, (published_ns - s) / 1e6) for s in self._pending.values()]
        self._pending.clear()
        self.stats.latencies_ms.extend(out)
        self.stats.published += 1
        return out

    def fused_message(self, stamp_ns: int, meta: dict[str, Any] | None = None) -> MapMessage:
        m = {"version": self.version}
        m.update(meta or {})
        return MapMessage(
            kind=MessageKind.FUSED_MAP,
            sender=self.sender,
            seq=self.version,
            stamp_ns=int(stamp_ns),
            pose=Pose.identity(),
            frame="fleet",
            origin=Pose.identity(),
            resolution=self.threshold,
            wireframe=self.fused,
            robots=self.fused_robots,
            meta=m,
        )

    def sim_time(self) -> float:
        """The latest simulated time any robot map carries (``meta["t"]``), 0 if none."""
        ts = [float(e.message.meta.get("t", 0.0)) for e in self.robots.values() if isinstance(e.message.meta, dict)]
        return max(ts, default=0.0)

    # ------------------------------------------------------------------ store
    def save(self, store: str | os.PathLike[str], robots: Iterable[str] | None = None, stamp_ns: int = 0) -> None:
        """Write the state under ``store`` atomically, file by file: ``robots/<id>.wfm`` (the bytes
        as received; only ``robots`` when given), ``fused.wfm`` and ``state.json`` last."""
        d = Path(store)
        for rid in sorted(self.robots if robots is None else robots):
            if rid in self.robots:
                write_atomic(d / "robots" / f"{rid}.wfm", self.robots[rid].raw)
        write_atomic(d / "fused.wfm", encode_message(self.fused_message(stamp_ns)))
        write_json(
            d / "state.json",
            {
                "version": self.version,
                "robots": {
                    r: {"seq": e.key[1], "boot": e.key[0], "sha256": e.key[2]} for r, e in sorted(self.robots.items())
                },
                "fused": {"vertices": self.fused.n_vertices, "edges": self.fused.n_edges},
                "stats": self.stats.as_dict(),
                "latencies_ms": [round(x, 3) for x in self.stats.latencies_ms[-100_000:]],
            },
        )

    @classmethod
    def load(
        cls,
        store: str | os.PathLike[str],
        config: FusionConfig | None = None,
        sender: str = FUSION_ID,
        merge_fn: MergeFn | None = None,
    ) -> FusionState:
        """Resume from :meth:`save`'s files (an absent or empty store gives a fresh state).

        The fused map is recomputed from the stored robot maps (so it is the same map) and keeps
        the stored version when it equals the stored fused map; otherwise the version goes up.
        Unreadable robot files are skipped with a warning on stderr.
        """
        st = cls(config, sender, merge_fn)
        d = Path(store)
        if not d.exists():
            return st
        if not d.is_dir():
            raise UserError(f"{d}: not a directory")
        for f in sorted((d / "robots").glob("*.wfm")):
            try:
                raw = f.read_bytes()
                msg = decode_message(raw)
            except (OSError, ValueError) as exc:
                sys.stderr.write(f"wiremap fuse: skipping {f}: {exc}\n")
                continue
            st._add(msg, raw)
        st.stats = FusionStats()
        version = 0
        old_fused: Wireframe | None = None
        try:
            state = json.loads((d / "state.json").read_text())
            version = int(state.get("version", 0))
            st.stats.latencies_ms = [float(x) for x in state.get("latencies_ms", [])]
        except (OSError, ValueError, TypeError, AttributeError):
            pass
        try:
            fm = decode_message((d / "fused.wfm").read_bytes())
            old_fused = fm.wireframe
            version = max(version, int(fm.seq))
        except (OSError, ValueError):
            pass
        if st.robots:
            st.fuse()
        st._pending.clear()
        same = False
        if old_fused is not None and st.robots:
            # compare as stored: through the codec
            again = decode_message(encode_message(st.fused_message(0))).wireframe
            same = again.almost_equal(old_fused, tol=1e-9, likelihood_tol=1e-9)
        st.version = version if (same or not st.robots) else version + 1
        return st


def _same_map(a: MapMessage, b: MapMessage) -> bool:
    return a.origin.almost_equal(b.origin, 1e-12, 1e-12) and a.wireframe.almost_equal(b.wireframe, tol=1e-12)


def _refine(source: Wireframe, target: Wireframe, threshold: float, cfg: FusionConfig) -> Pose | None:
    """A small rigid correction (fleet frame) of ``source`` onto ``target`` by
    :func:`mapping.icp.icp`, or None.

    ICP rotates about its frame's origin, so both maps are first expressed in a frame at the
    centroid of ``source``'s vertices and the correction is brought back to the fleet frame
    (``F * C * F^-1``). None when the module is absent, ICP does not accept its result, or the
    correction exceeds ``cfg.max_refine_m`` / ``cfg.max_refine_rad`` (the start pose alone is
    trusted then).
    """
    try:
        from mapping.icp import icp  # written by another helper
    except ImportError:
        return None
    if source.n_vertices == 0 or target.n_vertices == 0:
        return None
    c = source.points.mean(axis=0)
    F = Pose(float(c[0]), float(c[1]), 0.0)
    Finv = F.inverse()
    try:
        res = icp(source.transformed(Finv), target.transformed(Finv))
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not getattr(res, "accepted", False):
        return None
    pose = F.compose(res.correction).compose(Finv)
    if math.hypot(pose.x, pose.y) > cfg.max_refine_m or abs(pose.theta) > cfg.max_refine_rad:
        return None
    if math.hypot(pose.x, pose.y) < 1e-6 and abs(pose.theta) < 1e-7:
        return None
    return pose


# ---------------------------------------------------------------------- the zenoh shell
def _drain(q: queue.Queue[tuple[str, bytes]], timeout: float) -> list[tuple[str, bytes]]:
    """Everything in ``q``, waiting up to ``timeout`` for the first item."""
    try:
        out = [q.get(timeout=timeout)]
    except queue.Empty:
        return []
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out


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
        is always written at exit, so only a crash can lose up to this much).
    config : :class:`FusionConfig`.
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


class FusionService:
    """The Zenoh shell around :class:`FusionState` (see :func:`serve`)."""

    def __init__(self, session: Any, keys: Any, opts: ServeOptions, log: Callable[[str], None] | None = None) -> None:
        import zenoh

        self._zenoh = zenoh
        self.session = session
        self.keys = keys
        self.opts = opts
        self.say = log or (lambda _s: None)
        self.state = FusionState.load(opts.store, opts.config) if opts.store else FusionState(opts.config)
        self.recorder: Any = None
        if opts.rrd:
            from agents.rerun_log import FleetRecorder

            self.recorder = FleetRecorder(opts.rrd, serve_port=opts.serve_viewer, recording_id=opts.recording_id)
            if opts.world:
                try:
                    from agents.sim.world import load_world

                    self.recorder.log_truth(load_world(opts.world).truth)
                except (UserError, OSError, ValueError) as exc:
                    self.say(f"cannot draw the world {opts.world!r}: {exc}")
        self.lock = threading.Lock()
        self.current: bytes | None = None  # the last published fused map (the queryable's answer)
        self.version_stamp_ns = 0
        self.inbox: queue.Queue[tuple[str, bytes]] = queue.Queue()
        self.alive: set[str] = set()
        self.seen_alive: set[str] = set()
        self.stale: list[str] = []
        self.last_put = time.monotonic()
        self.last_fuse = 0.0
        self.last_say = 0.0
        self.dirty: set[str] = set()
        self.unsaved: set[str] = set()
        self.last_save = 0.0
        self._entities: list[Any] = []
        if self.state.version > 0 and self.state.robots:
            self.version_stamp_ns = time.time_ns()
            self.current = encode_message(self.state.fused_message(self.version_stamp_ns, self._meta()))
            self.say(f"resumed fused v{self.state.version} from {opts.store} ({len(self.state.robots)} robots)")

    # ------------------------------------------------------------------ zenoh callbacks (zenoh threads)
    def _on_map(self, sample: Any) -> None:
        self.inbox.put((str(sample.key_expr), sample.payload.to_bytes()))

    def _on_query(self, query: Any) -> None:
        with self.lock:
            data = self.current
        if data is not None:
            query.reply(self.keys.fused_map, data)

    def _on_alive(self, sample: Any) -> None:
        rid = self.keys.robot_of(str(sample.key_expr))
        if rid is None:
            return
        with self.lock:
            if sample.kind == self._zenoh.SampleKind.PUT:
                self.alive.add(rid)
                self.seen_alive.add(rid)
            else:
                self.alive.discard(rid)

    # ------------------------------------------------------------------ main thread
    def start(self) -> None:
        z = self._zenoh
        s = self.session
        # liveliness first, so the alive set is complete when the first maps come in
        self._entities.append(s.liveliness().declare_subscriber(self.keys.all_alive, self._on_alive, history=True))
        self._entities.append(s.declare_queryable(self.keys.fused_map, self._on_query, complete=True))
        self._entities.append(s.declare_subscriber(self.keys.all_maps, self._on_map))
        self.sub_pose = s.declare_subscriber(self.keys.all_poses, z.handlers.RingChannel(256))
        self.sub_viz = s.declare_subscriber(self.keys.all_viz, z.handlers.RingChannel(64))
        self._entities += [self.sub_pose, self.sub_viz]
        if self.current is not None:
            self._put(self.current)

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
        self._put(data)
        lat = st.take_latencies(time.time_ns())
        if self.recorder is not None:
            self.recorder.log_fused(st.sim_time(), st.fused, st.fused_robots, st.version, max(lat) if lat else None)
        now = time.monotonic()
        if now - self.last_say >= 1.0:
            self.last_say = now
            self.say(
                f"fused v{st.version}: {st.fused.n_vertices} vertices, {st.fused.n_edges} edges, "
                f"{len(data)} bytes, robots {' '.join(st.fused_robots)}"
            )

    def poll(self, timeout: float = 0.05) -> None:
        """One iteration: take the maps that arrived, fuse, publish, store, log."""
        st = self.state
        for key, data in _drain(self.inbox, timeout):
            rid = self.keys.robot_of(key)
            if st.offer(data, rid) and rid is not None:
                self.dirty.add(rid)
        now = time.monotonic()
        if self.dirty and now - self.last_fuse >= self.opts.min_interval_s:
            self.last_fuse = now
            changed = sorted(self.dirty)
            self.dirty.clear()
            if st.fuse():
                self._publish_new_version()
            self.unsaved.update(changed)
            if self.recorder is not None:
                for rid in changed:
                    if rid in st.robots:
                        t = float(st.robots[rid].message.meta.get("t", 0.0))
                        self.recorder.log_robot_map(rid, t, st.robot_in_fleet(rid))
        if self.opts.store and self.unsaved and time.monotonic() - self.last_save >= self.opts.save_interval_s:
            st.save(self.opts.store, sorted(self.unsaved), self.version_stamp_ns)
            self.unsaved.clear()
            self.last_save = time.monotonic()
        self._poll_side_channels()
        with self.lock:
            stale = sorted(r for r in st.fused_robots if r in self.seen_alive and r not in self.alive)
        if self.current is not None:
            if stale != self.stale:
                # same version and stamp, new metadata: robots that left are flagged
                self.stale = stale
                data = encode_message(st.fused_message(self.version_stamp_ns, self._meta()))
                with self.lock:
                    self.current = data
                self._put(data)
                if stale:
                    self.say(f"stale robots: {' '.join(stale)}")
            elif time.monotonic() - self.last_put > self.opts.heartbeat_s:
                self._put(self.current)  # maps are whole states: re-publishing is idempotent

    def _poll_side_channels(self) -> None:
        from agents.bus import decode_pose, decode_viz

        st = self.state
        poses: dict[str, dict[str, Any]] = {}
        while (s := self.sub_pose.handler.try_recv()) is not None:
            rid = self.keys.robot_of(str(s.key_expr))
            try:
                if rid is not None:
                    poses[rid] = decode_pose(s.payload.to_bytes())
            except ValueError:
                st.stats.malformed += 1
        viz: dict[str, dict[str, Any]] = {}
        while (s := self.sub_viz.handler.try_recv()) is not None:
            rid = self.keys.robot_of(str(s.key_expr))
            try:
                if rid is not None:
                    viz[rid] = decode_viz(s.payload.to_bytes())
            except ValueError:
                st.stats.malformed += 1
        if self.recorder is None:
            return
        for rid, p in sorted(poses.items()):
            origin = st.robots[rid].message.origin if rid in st.robots else None
            est = p["fleet"] if origin is None else origin.compose(p["odom"])
            self.recorder.log_robot_pose(rid, p["t"], est, p["truth"])
        for rid, v in sorted(viz.items()):
            if rid in st.robots:
                m = st.robots[rid].message
                self.recorder.log_robot_viz(rid, v["t"], m.origin, v["pose"], v["scan"], v["particles"], v["weights"])

    def close(self) -> None:
        """Fuse and publish the maps still queued, undeclare everything, save, close the
        recording."""
        st = self.state
        try:
            for key, data in _drain(self.inbox, 0.0):
                rid = self.keys.robot_of(key)
                if st.offer(data, rid) and rid is not None:
                    self.dirty.add(rid)
            if self.dirty:
                self.dirty.clear()
                if st.fuse():
                    self._publish_new_version()
        finally:
            for ent in reversed(self._entities):
                try:
                    ent.undeclare()
                except Exception:  # already undeclared or session closed
                    pass
            self._entities.clear()
            if self.opts.store:
                st.save(self.opts.store, None, self.version_stamp_ns)
            if self.recorder is not None:
                self.recorder.close()


def serve(
    session: Any, keys: Any, opts: ServeOptions, stop: threading.Event, log: Callable[[str], None] | None = None
) -> FusionState:
    """Run the fusion service on an open Zenoh session until ``stop`` is set.

    Maps arrive through a callback into an unbounded ``queue.Queue`` (a FIFO: nothing is
    dropped, and zenoh's thread only enqueues bytes); poses and visualisation through zenoh
    ring channels (only the latest matters). The main thread decodes, fuses, publishes, stores
    and logs; the queryable's callback answers with the last published bytes under a lock.
    Returns the final state (saved when ``opts.store`` is set).
    """
    svc = FusionService(session, keys, opts, log)
    try:
        svc.start()
        svc.say("fusion service ready")
        while not stop.is_set():
            svc.poll(0.05)
    finally:
        svc.close()
    return svc.state
