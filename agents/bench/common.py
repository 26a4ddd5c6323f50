"""Shared pieces of the fleet benchmarks (``wiremap bench fleet`` and ``wiremap bench soak``).

* **Recordings** (:class:`Recording`): the sequence of best maps of real filter runs, one per
  robot, recorded once per (world, fleet size, seed, particles, overlap, map resolution, merge
  threshold) and cached under
  ``out/bench-cache/`` so that a replay robot (:mod:`agents.bench.replay_robot`) can publish
  them at 10 Hz without running a filter. The routes are exactly those of ``wiremap run``
  (:func:`agents.sim.route.plan_routes` with the same seed and overlap; robot ``k`` gets filter
  seed ``seed + k``), so a replayed fleet maps what a real fleet of that size would map.
* **Processes** (:class:`Procs`): children started in their own session, stopped with SIGINT and
  then SIGKILL, always reaped; ``/proc`` readers for CPU time and RSS.
* **Bus observer** (:class:`BusObserver`): a Zenoh client of the benchmark itself that counts
  what the robots put on the bus (map and pose bytes, valid and corrupt map payloads).
* **Fusion store** readers: the fusion service records its counters in ``<store>/state.json``
  and every publish latency in ``<store>/latency.log`` (:class:`agents.fleet.fusion.StoreJob`); the
  benchmarks read them there, as ``wiremap run`` does for ``report.json``.

Nothing here imports zenoh at module level (the CLI must stay light).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from agents.errors import UserError
from agents.files.io import write_atomic
from agents.fleet.proc import rss_kb, stop_processes
from mapping.se2 import Pose
from mapping.wireframe import Wireframe

REPO = Path(__file__).resolve().parent.parent.parent
DEFAULT_CACHE = Path("out") / "bench-cache"
RECORDING_FORMAT = "wiremap-replay/1"
RECORD_VERSION = 2  # bump when the recorder changes what it records (invalidates the cache)
DEFAULT_OVERLAP = 0.15  # as ``wiremap run``
DEFAULT_PARTICLES = 5  # as ``wiremap run``
DEFAULT_THRESHOLD = 0.2  # the robot agent's default merge threshold
DEFAULT_RESOLUTION = 0.05  # the robot agent's default map resolution (quantisation step)


# ---------------------------------------------------------------------- recordings
@dataclass(frozen=True)
class Frame:
    """One recorded step: sim time, the filter's pose (odometry frame), the true pose (world
    frame) and the best map (odometry frame), as it would travel (codec-quantised)."""

    t: float
    pose: Pose
    truth: Pose | None
    wireframe: Wireframe


@dataclass(frozen=True)
class Recording:
    """A robot's recorded run: its id, world, start pose in the fleet frame (the map origin),
    map resolution (the quantisation step of its maps on the wire), and the frames whose
    travelling map differs from the previous frame's; ``threshold`` is the filter's merge
    threshold (None in recordings that did not say)."""

    robot: str
    world: str
    start: Pose
    resolution: float
    frames: tuple[Frame, ...]
    steps: int  # filter steps run, including those whose map did not change
    threshold: float | None = None


def _pose_list(p: Pose | None) -> list[float] | None:
    return None if p is None else [float(v) for v in p.as_tuple()]


def save_recording(path: str | os.PathLike[str], rec: Recording) -> None:
    """Write a recording (msgpack; each frame's map as ``wire_codec`` bytes), atomically."""
    from agents.fleet.robot import robot_map_message
    from wire_codec import encode

    frames = []
    for k, f in enumerate(rec.frames):
        msg = robot_map_message(rec.robot, rec.start, rec.resolution, f.wireframe, f.pose, k + 1, 0, {})
        frames.append({"t": float(f.t), "pose": _pose_list(f.pose), "truth": _pose_list(f.truth),
                       "map": encode(msg)})
    doc = {
        "format": RECORDING_FORMAT,
        "robot": rec.robot,
        "world": rec.world,
        "start": _pose_list(rec.start),
        "resolution": float(rec.resolution),
        "threshold": None if rec.threshold is None else float(rec.threshold),
        "steps": int(rec.steps),
        "frames": frames,
    }
    write_atomic(path, bytes(msgpack.packb(doc, use_bin_type=True)))


def load_recording(path: str | os.PathLike[str]) -> Recording:
    """Read :func:`save_recording`'s file. Raises ``UserError`` when it is not one."""
    from wire_codec import decode

    try:
        doc = msgpack.unpackb(Path(path).read_bytes(), raw=False)
        if not isinstance(doc, dict) or doc.get("format") != RECORDING_FORMAT:
            raise ValueError(f"not a {RECORDING_FORMAT} file")
        frames = []
        for f in doc["frames"]:
            m = decode(f["map"])
            truth = None if f.get("truth") is None else Pose(*map(float, f["truth"]))
            frames.append(Frame(float(f["t"]), Pose(*map(float, f["pose"])), truth, m.wireframe))
        if not frames:
            raise ValueError("no frames")
        return Recording(
            robot=str(doc["robot"]),
            world=str(doc["world"]),
            start=Pose(*map(float, doc["start"])),
            resolution=float(doc["resolution"]),
            frames=tuple(frames),
            steps=int(doc.get("steps", len(frames))),
            threshold=None if doc.get("threshold") is None else float(doc["threshold"]),
        )
    except OSError as exc:
        raise UserError(f"{path}: {exc.strerror or exc}") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise UserError(f"{path}: not a replay recording: {exc}") from None


def fleet_routes(world: Any, n: int, seed: int, overlap: float = DEFAULT_OVERLAP) -> list[np.ndarray]:
    """The routes ``wiremap run --robots n --seed seed`` gives its robots."""
    from agents.sim.route import plan_routes

    try:
        return plan_routes(world, n, np.random.default_rng(seed), overlap=overlap)
    except ValueError as exc:
        raise UserError(f"cannot plan routes in {world.name}: {exc}") from None


def record_robot(
    world_spec: str,
    robot: str,
    route: np.ndarray,
    seed: int,
    particles: int = DEFAULT_PARTICLES,
    resolution: float = DEFAULT_RESOLUTION,
    threshold: float = DEFAULT_THRESHOLD,
) -> Recording:
    """Run the robot agent's simulation + filter loop (:func:`agents.fleet.robot.default_steps`,
    merge threshold ``threshold``) along ``route`` and keep the best map after every step
    whose travelling (codec) form at ``resolution`` changed, as the robot agent would publish it.

    The origin is the first true pose (what :class:`agents.fleet.robot.RobotAgent` does when the
    simulator knows it)."""
    from agents.fleet.robot import RobotOptions, default_steps, robot_map_message, start_pose_of
    from wire_codec import decode, encode

    opts = RobotOptions(
        robot=robot, world=world_spec, start=start_pose_of(route), route=route, seed=seed,
        particles=particles, resolution=resolution, threshold=threshold,
    )
    frames: list[Frame] = []
    last: bytes | None = None
    start: Pose | None = None
    steps = 0
    for s in default_steps(opts):
        steps += 1
        if start is None:
            start = s.true_pose if s.true_pose is not None else opts.start
        msg = robot_map_message(robot, start, resolution, s.filter.best, Pose.identity(), 0, 0, {})
        data = encode(msg)
        if data == last:
            continue
        last = data
        frames.append(Frame(float(s.t), s.pose, s.true_pose, decode(data).wireframe))
    if start is None or not frames:
        raise UserError(f"recording {robot} in {world_spec}: the route gave no scans")
    return Recording(robot, world_spec, start, resolution, tuple(frames), steps, threshold)


def _world_fingerprint(world_spec: str) -> str:
    p = Path(world_spec)
    if p.is_file():
        return hashlib.sha256(p.read_bytes()).hexdigest()[:16]
    return world_spec


def recordings_for(
    world_spec: str,
    n: int,
    seed: int,
    cache: str | os.PathLike[str] = DEFAULT_CACHE,
    particles: int = DEFAULT_PARTICLES,
    overlap: float = DEFAULT_OVERLAP,
    resolution: float = DEFAULT_RESOLUTION,
    say: Callable[[str], None] | None = None,
    threshold: float | None = None,
) -> list[Path]:
    """Paths of the recordings of robots ``r1..rn`` of a fleet of ``n`` (recorded now unless
    cached). The cache directory's name carries a hash of everything that affects them.
    ``threshold``: the filters' merge threshold (default: the world's,
    :func:`agents.mapping_run.default_merge_threshold`)."""
    from agents.mapping_run import default_merge_threshold
    from agents.sim.world import load_world

    world = load_world(world_spec)
    thr = float(threshold) if threshold is not None else default_merge_threshold(world)
    key = json.dumps(
        [RECORD_VERSION, _world_fingerprint(world_spec), n, seed, particles, overlap, resolution, thr],
        sort_keys=True
    )
    h = hashlib.sha256(key.encode()).hexdigest()[:12]
    d = Path(cache) / f"{world.name}-n{n}-s{seed}-{h}"
    paths = [d / f"r{k + 1}.wrp" for k in range(n)]
    if all(p.is_file() for p in paths):
        return paths
    routes = fleet_routes(world, n, seed, overlap)
    t0 = time.monotonic()
    for k, (p, r) in enumerate(zip(paths, routes)):
        if p.is_file():
            continue
        rec = record_robot(world_spec, f"r{k + 1}", r, seed + k + 1, particles, resolution, thr)
        save_recording(p, rec)
    if say is not None:
        say(f"recorded {n} robots' maps in {world.name} ({time.monotonic() - t0:.1f} s) into {d}")
    return paths


# ---------------------------------------------------------------------- /proc readers
def rss_bytes(pid: int) -> int | None:
    """Resident set size of a live process in bytes (:func:`agents.fleet.proc.rss_kb`), or None."""
    kb = rss_kb(pid)
    return None if kb is None else kb * 1024


# ---------------------------------------------------------------------- processes
def child_env() -> dict[str, str]:
    """The environment of benchmark children: the repo importable, unbuffered output, one BLAS
    thread (two cores: no oversubscription), Rerun analytics off."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RERUN_ANALYTICS", "0")
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env[var] = "1"
    return env


class Procs:
    """Child processes of one benchmark run, each in its own session with its output in
    ``logs/<name>.log``. ``with Procs(logs) as procs:`` stops whatever is left on exit (SIGINT,
    then SIGKILL of the process group after a grace period) and reaps everything."""

    def __init__(self, logs: str | os.PathLike[str]) -> None:
        self.logs = Path(logs)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.exit_codes: dict[str, int | None] = {}

    def __enter__(self) -> Procs:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop(list(self.procs), timeout=10.0)

    def log_path(self, name: str) -> Path:
        return self.logs / f"{name}.log"

    def log(self, name: str) -> str:
        try:
            return self.log_path(name).read_text(errors="replace")
        except OSError:
            return ""

    def start(self, name: str, argv: Sequence[str], prefix: Sequence[str] = ()) -> subprocess.Popen[bytes]:
        """Start ``[*prefix, python, *argv]`` (``argv`` e.g. ``["-m", "agents", "fuse", ...]``);
        ``prefix`` e.g. ``["ip", "netns", "exec", NS]``. Appends to the log (restarts keep it)."""
        self.logs.mkdir(parents=True, exist_ok=True)
        with open(self.log_path(name), "ab") as fh:
            p = subprocess.Popen(
                [*prefix, sys.executable, *argv],
                stdout=fh,
                stderr=subprocess.STDOUT,
                env=child_env(),
                start_new_session=True,
            )
        self.procs[name] = p
        return p

    def pid(self, name: str) -> int:
        return self.procs[name].pid

    def alive(self, name: str) -> bool:
        p = self.procs.get(name)
        return p is not None and p.poll() is None

    def dead(self) -> list[str]:
        return [n for n, p in self.procs.items() if p.poll() is not None]

    def kill(self, name: str) -> None:
        """SIGKILL (the process group) and reap."""
        p = self.procs.pop(name)
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        p.wait()
        self.exit_codes[name] = p.returncode

    def signal(self, names: Sequence[str], sig: int) -> None:
        for n in names:
            p = self.procs.get(n)
            if p is not None and p.poll() is None:
                try:
                    p.send_signal(sig)
                except ProcessLookupError:
                    pass

    def stop(self, names: Sequence[str], timeout: float = 15.0) -> dict[str, int | None]:
        """SIGINT to ``names`` together, wait up to ``timeout`` s, then SIGKILL; all reaped.
        Returns the exit codes (None: had to be killed)."""
        names = [n for n in names if n in self.procs]
        out = stop_processes(self.procs, names, timeout)
        for n in names:
            self.procs.pop(n)
        self.exit_codes.update(out)
        return out

    def wait_log(self, name: str, text: str, timeout: float) -> None:
        """Wait until ``text`` is in ``name``'s log; ``UserError`` if it exits or time runs out."""
        deadline = time.monotonic() + timeout
        while text not in self.log(name):
            p = self.procs.get(name)
            if p is None or p.poll() is not None:
                raise UserError(f"{name} exited before {text!r} (see {self.log_path(name)})")
            if time.monotonic() > deadline:
                raise UserError(f"{name}: no {text!r} after {timeout:g} s (see {self.log_path(name)})")
            time.sleep(0.05)


def wait_for(procs: Procs, cond: Any, timeout: float, what: str, step: float = 0.05) -> None:
    """Poll ``cond`` until true; ``UserError`` when a process dies or ``timeout`` passes."""
    deadline = time.monotonic() + timeout
    while not cond():
        dead = procs.dead()
        if dead:
            raise UserError(f"{', '.join(dead)} exited while waiting for {what} (see {procs.logs})")
        if time.monotonic() > deadline:
            raise UserError(f"timed out after {timeout:g} s waiting for {what} (see {procs.logs})")
        time.sleep(step)


def sleep_checked(procs: Procs, seconds: float) -> None:
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        dead = procs.dead()
        if dead:
            raise UserError(f"{', '.join(dead)} exited during the run (see {procs.logs})")
        time.sleep(min(0.2, left))



# ---------------------------------------------------------------------- the bus observer
def crc_ok(data: bytes) -> bool:
    """Whether a payload passes the wire codec's envelope CRC (``wire_codec/FORMAT.md`` sec. 2:
    the message ends with ``0xce`` + big-endian CRC-32 of every byte before it). A cheap
    validity test for counting: corrupted payloads (a flipped byte, a truncation) fail it."""
    if len(data) < 20 or data[-5] != 0xCE:
        return False
    return (zlib.crc32(data[:-5]) & 0xFFFFFFFF) == struct.unpack(">I", data[-4:])[0]


@dataclass
class RobotCounts:
    maps: int = 0
    valid: int = 0
    corrupt: int = 0
    map_bytes: int = 0
    poses: int = 0
    pose_bytes: int = 0
    first_map: float | None = None
    last_map: float | None = None


class BusObserver:
    """A Zenoh client of the benchmark: counts, per robot, what arrives on ``robots/*/map``
    (payloads, bytes, valid by :func:`crc_ok` or corrupt) and ``robots/*/pose``; while
    :attr:`keep` is set it also keeps the map payloads (for the occupancy-grid comparison).

    Use as a context manager; the session and subscribers are closed on exit."""

    def __init__(self, endpoint: str, fleet: str, timeout: float = 30.0) -> None:
        from agents.fleet.bus import FleetKeys, build_config, open_session

        self.keys = FleetKeys(fleet)
        self.lock = threading.Lock()
        self.counts: dict[str, RobotCounts] = {}
        self.window: dict[str, RobotCounts] | None = None
        self.kept: list[tuple[str, bytes]] = []
        self.keep = False
        self.session = open_session(build_config("client", None, [endpoint]), timeout=timeout)
        assert self.session is not None
        self._subs = [
            self.session.declare_subscriber(self.keys.all_maps, self._on_map),
            self.session.declare_subscriber(self.keys.all_poses, self._on_pose),
        ]

    def __enter__(self) -> BusObserver:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # already closed
                pass
        self._subs = []
        if self.session is not None:
            self.session.close()
            self.session = None

    def _entries(self, rid: str) -> list[RobotCounts]:
        out = [self.counts.setdefault(rid, RobotCounts())]
        if self.window is not None:
            out.append(self.window.setdefault(rid, RobotCounts()))
        return out

    def _on_map(self, sample: Any) -> None:
        rid = self.keys.robot_of(str(sample.key_expr)) or "?"
        data = sample.payload.to_bytes()
        ok = crc_ok(data)
        now = time.monotonic()
        with self.lock:
            for c in self._entries(rid):
                c.maps += 1
                c.valid += ok
                c.corrupt += not ok
                c.map_bytes += len(data)
                c.first_map = now if c.first_map is None else c.first_map
                c.last_map = now
            if self.keep and ok:
                self.kept.append((rid, data))

    def _on_pose(self, sample: Any) -> None:
        rid = self.keys.robot_of(str(sample.key_expr)) or "?"
        n = len(sample.payload.to_bytes())
        with self.lock:
            for c in self._entries(rid):
                c.poses += 1
                c.pose_bytes += n

    def fusion_stats(self, timeout: float = 2.0) -> dict[str, Any]:
        """The fusion service's counters document (``fused/stats``), or {} without an answer."""
        if self.session is None:
            return {}
        try:
            for reply in self.session.get(self.keys.fusion_stats, timeout=timeout):
                ok = reply.ok
                if ok is not None:
                    doc = json.loads(ok.payload.to_bytes())
                    return doc if isinstance(doc, dict) else {}
        except Exception:  # no answer in time, or the session is closing
            return {}
        return {}

    def start_window(self, keep: bool = False) -> None:
        with self.lock:
            self.window = {}
            self.keep = keep
            self.kept = []

    def end_window(self) -> dict[str, RobotCounts]:
        with self.lock:
            w, self.window, self.keep = self.window or {}, None, False
        return w

    def seen(self) -> set[str]:
        """Robots whose valid map has arrived."""
        with self.lock:
            return {r for r, c in self.counts.items() if c.valid}

    def snapshot(self) -> dict[str, RobotCounts]:
        with self.lock:
            return {r: RobotCounts(**vars(c)) for r, c in self.counts.items()}


def grid_bytes(wf: Wireframe, resolution: float) -> int:
    """Bytes of the same map as a raw int8 occupancy grid over its bounding box at
    ``resolution`` (one byte per cell, ``ceil(w / r) * ceil(h / r)`` cells, at least one)."""
    if wf.n_vertices == 0 or not resolution > 0:
        return 0
    xmin, ymin = wf.points.min(axis=0)
    xmax, ymax = wf.points.max(axis=0)
    nx = max(1, math.ceil((float(xmax) - float(xmin)) / resolution - 1e-9))
    ny = max(1, math.ceil((float(ymax) - float(ymin)) / resolution - 1e-9))
    return int(nx * ny)


# ---------------------------------------------------------------------- the fusion store
def read_state(store: str | os.PathLike[str]) -> dict[str, Any]:
    """``<store>/state.json`` as written by the fusion service ({} while there is none; a
    half-written file cannot be read, the writes are atomic)."""
    try:
        doc = json.loads((Path(store) / "state.json").read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def latency_total(state: dict[str, Any]) -> int:
    """How many publish latencies the fusion service has recorded, all-time
    (``state.json``'s ``latency_total``; older stores: ``stats.latency_ms.total`` or ``n``)."""
    lat = (state.get("stats") or {}).get("latency_ms") or {}
    for v in (state.get("latency_total"), lat.get("total"), lat.get("n")):
        if v is not None:
            try:
                return int(v)
            except (TypeError, ValueError):
                continue
    return 0


class LatencyHarvest:
    """Collects the fusion service's publish latencies over a run from ``<store>/latency.log``
    (:func:`agents.fleet.fusion.append_latency_log`: one line ``<index> <ms> <published_ns>`` per
    sample, ``index`` counting every sample ever recorded; the file is rotated to
    ``latency.log.1``; the service appends at its store interval, about once a second).

    Samples with an index up to ``latency_total`` at construction are left out (recorded
    before). :meth:`poll` reads what was appended since the last poll (call it now and then:
    after a rotation it reads the rest of the old file, but a second rotation before the next
    poll would lose samples); a gap in the indices counts as :attr:`missed`.
    :meth:`between` selects the samples by the wall-clock time of their fused publish.
    """

    def __init__(self, store: str | os.PathLike[str]) -> None:
        self.store = Path(store)
        self.last_index = latency_total(read_state(self.store))
        self.records: list[tuple[int, float]] = []  # (published_ns or 0, ms)
        self.missed = 0  # recorded but gone (rotated away twice) before a poll
        self._offsets: dict[int, int] = {}  # inode -> bytes consumed

    @property
    def samples(self) -> list[float]:
        return [ms for _, ms in self.records]

    def between(self, t0_ns: int, t1_ns: int) -> list[float]:
        """The samples whose fused publish was within ``[t0_ns, t1_ns]`` (wall clock; samples
        without a time are kept)."""
        return [ms for t, ms in self.records if t == 0 or t0_ns <= t <= t1_ns]

    def poll(self) -> None:
        from agents.fleet.fusion import LATENCY_LOG

        seen: dict[int, int] = {}
        for name in (LATENCY_LOG + ".1", LATENCY_LOG):  # the rotated (older) file first
            path = self.store / name
            try:
                with open(path, "rb") as fh:
                    ino = os.fstat(fh.fileno()).st_ino
                    off = self._offsets.get(ino, 0)
                    fh.seek(off)
                    data = fh.read()
            except OSError:
                continue
            end = data.rfind(b"\n") + 1  # complete lines only
            self._take(data[:end])
            seen[ino] = off + end
        self._offsets = seen

    def _take(self, data: bytes) -> None:
        for ln in data.split(b"\n"):
            parts = ln.split()
            if len(parts) not in (2, 3):
                continue
            try:
                idx, ms = int(parts[0]), float(parts[1])
                t = int(parts[2]) if len(parts) == 3 else 0
            except ValueError:
                continue
            if idx <= self.last_index:
                continue
            self.missed += idx - self.last_index - 1
            self.last_index = idx
            self.records.append((t, ms))


def merge_counts(stats: dict[str, Any]) -> dict[str, int]:
    """The fusion service's map counters (:class:`agents.fleet.fusion.FusionStats`), summed into
    what the benchmarks report:

    * ``arrived``: map payloads that reached the service: those its intake dropped before
      decoding (``oversized``, ``rate_limited``, ``overflow``) plus those it decoded
      (``received``);
    * ``merged``: valid robot maps the service took in: ``accepted`` (became that robot's
      latest map) + ``outdated`` (arrived after a newer map of the same robot: already
      superseded) + ``duplicates`` (the same map again) + ``superseded`` (a newer map of the
      same robot arrived in the same batch, so it was not decoded; its envelope and CRC hold:
      a damaged payload is counted ``malformed`` even then);
    * ``dropped``: ``arrived - merged``: malformed, rejected, absurd, and the intake's drops.
      An intake ``overflow`` may be a map superseded in the queue by a newer one of its robot,
      but the counter does not tell, so it counts as dropped (and shows as lost when valid).
    """

    def get(k: str) -> int:
        try:
            return int(stats.get(k, 0) or 0)
        except (TypeError, ValueError):
            return 0

    received = get("received")
    arrived = received + get("oversized") + get("rate_limited") + get("overflow")
    merged = get("accepted") + get("outdated") + get("duplicates") + get("superseded")
    return {
        "arrived": arrived,
        "received": received,
        "merged": merged,
        "dropped": arrived - merged,
        "overflow": get("overflow"),
        "rate_limited": get("rate_limited"),
    }


def percentile(values: Sequence[float], q: float) -> float | None:
    if len(values) == 0:
        return None
    return float(np.percentile(np.asarray(values, dtype=np.float64), q))


# ---------------------------------------------------------------------- output
def print_table(head: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """An aligned text table on stdout (first column left-aligned, the others right)."""

    def fmt(v: Any) -> str:
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v)

    cells = [list(head)] + [[fmt(v) for v in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(head))]
    for r in cells:
        print("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))))
    sys.stdout.flush()


class Progress:
    """One live line on stderr, cut to the terminal's width (a line per run when stderr is not
    a terminal or several logs run at once)."""

    def __init__(self, enabled: bool, live: bool) -> None:
        self.enabled = enabled
        self.live = live and enabled and sys.stderr.isatty()
        self._last = 0.0
        self._shown = False

    def update(self, text: str) -> None:
        if not self.live:
            return
        now = time.monotonic()
        if now - self._last < 0.2:
            return
        self._last = now
        cols = shutil.get_terminal_size((80, 24)).columns - 1
        sys.stderr.write("\r" + text[:cols].ljust(cols))
        sys.stderr.flush()
        self._shown = True

    def clear(self) -> None:
        """Erase the live line, if one is shown."""
        if self._shown:
            sys.stderr.write("\r" + " " * (shutil.get_terminal_size((80, 24)).columns - 1) + "\r")
            sys.stderr.flush()
            self._shown = False

    def line(self, text: str) -> None:
        if not self.enabled:
            return
        self.clear()
        sys.stderr.write(text + "\n")
        sys.stderr.flush()


def aligned_rows(rows: Sequence[Sequence[str]], left: int = 1) -> str:
    """``rows`` (the head first) as text columns: the first ``left`` columns flush left, the
    others flush right, two spaces apart."""
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return "\n".join(
        "  ".join(c.ljust(w) if i < left else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))
        for row in rows
    )


def fmt_cell(v: Any, f: str) -> str:
    """``v`` formatted by ``f`` (``"{:.3f}"``), or ``-`` when there is none or it is not finite."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f.format(v)


def rounded(v: float | None, nd: int = 3) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), nd)
