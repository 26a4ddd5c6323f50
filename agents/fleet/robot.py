"""The robot agent: one simulated robot with its own wireframe particle filter, on the bus.

One OS process per robot (``wiremap robot``). The simulation and the filter come from
:mod:`agents.mapping_run` (the same loop as ``wiremap map``); this module is the shell that paces
it in real time and publishes, under ``wiremap/<fleet>/``:

* ``robots/<id>/map``: the best particle's wireframe as a ``ROBOT_MAP`` (wire codec), in the
  robot's odometry frame (the frame of its first pose), with its start pose in the fleet frame
  as ``origin`` (the known-start-pose case), quantised at ``resolution`` (0.05 m; the filter
  merges at ``threshold``, 0.2 m). Sent when it changes *as it travels* (the codec's
  quantised form differs from the last one sent) and at least every ``heartbeat_s`` seconds
  (maps are whole states: re-sending is idempotent). ``seq`` counts maps sent;
  ``meta = {"boot": <process start ns>, "t": <sim s>, "step": k}``; ``stamp_ns`` is the wall
  clock at the send (the fusion service measures its latency against it).
* ``robots/<id>/pose`` at ``pose_hz`` (10 Hz): :func:`agents.fleet.bus.encode_pose`, with a status map
  (step, vertices, edges, maps_sent, bytes_sent, finished) that ``wiremap run`` displays.
* ``robots/<id>/viz`` at ``viz_hz``: the current scan and every particle, for the recorder.
* ``alive/<id>``: a liveliness token for as long as the process runs.

The origin is the robot's true first pose when the simulator knows it (see
:meth:`RobotAgent._check_start`). Pacing: a scan every ``1 / rate`` s of wall time; when a step takes longer
the robot simply
falls behind (no step is skipped). When the route ends the robot stays on the bus (token, pose,
heartbeat maps) until stopped.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from wire_codec.message import MapMessage, MessageKind


class StepLike(Protocol):
    """What the robot needs from one simulation step (:class:`agents.mapping_run.RunStep`)."""

    @property
    def t(self) -> float: ...
    @property
    def true_pose(self) -> Pose | None: ...
    @property
    def pose(self) -> Pose: ...
    @property
    def scan(self) -> Wireframe: ...
    @property
    def filter(self) -> Any: ...


DEFAULT_RESOLUTION = 0.05  # quantisation step of the published map (GMapping's default cell)
DEFAULT_THRESHOLD = 0.2  # the filter's merge threshold (the paper's, for a small world)


@dataclass
class RobotOptions:
    """A robot agent's settings (see ``wiremap robot --help``).

    ``resolution`` is the quantisation step of the map's coordinates on the wire (the
    codec's ``resolution``); ``threshold`` is the particle filter's merge threshold. They
    are separate: a fine quantisation keeps the filter's centimetre accuracy while walls
    still merge at the paper's threshold. ``filter_overrides`` are further filter settings
    by dotted key (``{"compass.young_weight": 0.0}``, :func:`mapping.config.with_overrides`)."""

    robot: str
    world: str
    start: Pose
    route: NDArray[np.float64] | None = None
    rate: float = 5.0
    seed: int = 0
    particles: int = 5
    resolution: float = DEFAULT_RESOLUTION
    threshold: float = DEFAULT_THRESHOLD
    heartbeat_s: float = 2.0
    pose_hz: float = 10.0
    viz_hz: float = 2.0
    duration: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    filter_overrides: dict[str, Any] = field(default_factory=dict)
    unknown_start: bool = False  # publish in its own frame: origin identity, meta origin_unknown
    carmen: str | None = None  # replay this CARMEN log instead of simulating (agents.fleet.carmen_fleet)
    scans: tuple[int, int] | None = None  # the log's scans [i0, i1) this robot replays
    lidar_profile: str = "lidar-slam"  # the replayed scans' real-lidar profile (mapping_run.LIDAR_PROFILES)
    #: the robot's own lidar, live: (scan key, odometry key) on Zenoh (agents.fleet.live_lidar);
    #: ``rate`` is then 0 (each scan is mapped as it comes)
    live: tuple[str, str] | None = None
    mount: Pose = field(default_factory=Pose)  # with ``live``: the laser's pose on the robot's base
    #: False when ``--start`` gave no heading: the simulated robot's heading (along its route)
    #: is taken without a word.
    heading_given: bool = True


@dataclass
class RobotStatus:
    step: int = 0
    t: float = 0.0
    vertices: int = 0
    edges: int = 0
    maps_sent: int = 0
    bytes_sent: int = 0
    pose_bytes: int = 0
    viz_bytes: int = 0
    finished: bool = False
    step_ms: float = 0.0
    live: dict[str, Any] | None = None  # a live lidar's counters (agents.fleet.live_lidar.LiveCounts)

    def as_dict(self) -> dict[str, Any]:
        extra = {} if self.live is None else {"live": dict(self.live)}
        return {
            "step": self.step,
            "t": round(self.t, 3),
            "vertices": self.vertices,
            "edges": self.edges,
            "maps_sent": self.maps_sent,
            "bytes_sent": self.bytes_sent,
            "pose_bytes": self.pose_bytes,
            "viz_bytes": self.viz_bytes,
            "finished": self.finished,
            "step_ms": round(self.step_ms, 2),
            **extra,
        }


def robot_map_message(
    robot: str, origin: Pose, resolution: float, wf: Wireframe, pose: Pose, seq: int, stamp_ns: int,
    meta: dict[str, Any],
) -> MapMessage:
    """The ``ROBOT_MAP`` of robot ``robot`` for ``wf`` (frame ``odom/<robot>``, contributor bits
    cleared: a robot map has none)."""
    if wf.n_edges and wf.sources.any():
        wf = wf.replace(sources=np.zeros(wf.n_edges, dtype=np.uint64))
    return MapMessage(
        kind=MessageKind.ROBOT_MAP,
        sender=robot,
        seq=int(seq),
        stamp_ns=int(stamp_ns),
        pose=pose,
        frame=f"odom/{robot}",
        origin=origin,
        resolution=float(resolution),
        wireframe=wf,
        meta=dict(meta),
    )


def map_message(
    opts: RobotOptions, wf: Wireframe, pose: Pose, seq: int, stamp_ns: int, meta: dict[str, Any]
) -> MapMessage:
    """The ``ROBOT_MAP`` the agent with options ``opts`` sends for ``wf`` (with an unknown
    start: origin the identity, ``meta["origin_unknown"] = True``)."""
    if opts.unknown_start:
        return robot_map_message(
            opts.robot, Pose.identity(), opts.resolution, wf, pose, seq, stamp_ns,
            {**meta, "origin_unknown": True}
        )
    return robot_map_message(opts.robot, opts.start, opts.resolution, wf, pose, seq, stamp_ns, meta)


class KeyPut:
    """``session.put`` on one key with fixed options: the part of a publisher the robot and the
    benchmarks' replay robots use. Plain puts, not declared publishers: under the fleet ACL a
    declared publisher delivered only its first sample."""

    def __init__(self, session: Any, key: str, **options: Any) -> None:
        self.session = session
        self.key = key
        self.options = options

    def put(self, data: bytes) -> None:
        self.session.put(self.key, data, **self.options)

    def undeclare(self) -> None:
        pass


def robot_puts(session: Any, keys: Any, robot: str) -> dict[str, KeyPut]:
    """The puts of robot ``robot``: ``map`` (``CongestionControl.BLOCK``), ``pose`` (express)
    and ``viz``. Plain session puts, not declared publishers: a declared publisher filters on
    the writer side and so needs to see the subscribers' declarations, which the fleet ACL
    (agents.fleet.secure.acl_config) does not forward to robots -- on a secure router it delivered
    only its first sample."""
    import zenoh

    return {
        "map": KeyPut(session, keys.robot_map(robot), congestion_control=zenoh.CongestionControl.BLOCK),
        "pose": KeyPut(session, keys.robot_pose(robot), express=True),
        "viz": KeyPut(session, keys.robot_viz(robot)),
    }


def default_steps(opts: RobotOptions) -> Iterator[StepLike]:
    """The simulation + filter loop of :mod:`agents.mapping_run` for this robot (merge
    threshold ``opts.threshold``); with ``opts.carmen`` the replay of its stretch of the log."""
    from agents import mapping_run

    if opts.carmen is not None:
        from agents.fleet import carmen_fleet

        return carmen_fleet.robot_steps(opts)

    return mapping_run.robot_steps(opts)


class RobotAgent:
    """The Zenoh shell of one robot (see the module docstring).

    Parameters
    ----------
    session : an open Zenoh session.
    keys : :class:`agents.fleet.bus.FleetKeys`.
    opts : :class:`RobotOptions`.
    steps : the step iterator (default :func:`default_steps`).
    log : one-line progress messages.
    """

    def __init__(
        self,
        session: Any,
        keys: Any,
        opts: RobotOptions,
        steps: Iterator[StepLike | None] | None = None,
        log: Callable[[str], None] | None = None,
        live_counts: Callable[[], dict[str, Any]] | None = None,
    ) -> None:
        from wire_codec import encode

        self._encode = encode
        self.session = session
        self.keys = keys
        self.opts = opts
        self.say = log or (lambda _s: None)
        self.steps: Iterator[StepLike | None] = steps if steps is not None else default_steps(opts)
        self.live_counts = live_counts
        self.boot = time.time_ns()
        self.status = RobotStatus()
        self.last: StepLike | None = None
        self._last_body: bytes | None = None
        self._last_map_put = -math.inf
        self._token: Any = None
        self._pubs: dict[str, Any] = {}

    def start(self) -> None:
        self._token = self.session.liveliness().declare_token(self.keys.alive(self.opts.robot))
        self._pubs = robot_puts(self.session, self.keys, self.opts.robot)
        self._last_map_put = time.monotonic()  # the first map goes out with the first step

    def close(self) -> None:
        for p in self._pubs.values():
            try:
                p.undeclare()
            except Exception:  # session already closed
                pass
        self._pubs.clear()
        if self._token is not None:
            try:
                self._token.undeclare()
            except Exception:
                pass
            self._token = None

    # ------------------------------------------------------------------ publishing
    def _meta(self) -> dict[str, Any]:
        return {"boot": self.boot, "t": round(self.status.t, 6), "step": self.status.step}

    def publish_map(self, force: bool = False) -> bool:
        """Send the best map if its travelling form changed (or ``force``). Returns whether sent."""
        if self.last is None:
            return False
        best: Wireframe = self.last.filter.best
        pose: Pose = self.last.pose
        # compare what would travel, without the envelope fields that always change
        probe = self._encode(map_message(self.opts, best, pose, 0, 0, {}))
        if not force and probe == self._last_body:
            return False
        seq = self.status.maps_sent + 1
        data = self._encode(map_message(self.opts, best, pose, seq, time.time_ns(), self._meta()))
        self._pubs["map"].put(data)
        self._last_body = probe
        self._last_map_put = time.monotonic()
        self.status.maps_sent = seq
        self.status.bytes_sent += len(data)
        return True

    def publish_pose(self) -> None:
        from agents.fleet.bus import encode_pose

        if self.last is None:
            odom, truth, t = Pose.identity(), None, 0.0
        else:
            odom, truth, t = self.last.pose, self.last.true_pose, self.last.t
        data = encode_pose(
            seq=self.status.step,
            t=t,
            stamp_ns=time.time_ns(),
            odom=odom,
            fleet=odom if self.opts.unknown_start else self.opts.start.compose(odom),
            truth=truth,
            status=self.status.as_dict(),
        )
        self._pubs["pose"].put(data)
        self.status.pose_bytes += len(data)

    def publish_viz(self) -> None:
        from agents.fleet.bus import encode_viz

        if self.last is None:
            return
        f = self.last.filter
        data = encode_viz(
            t=self.last.t, scan=self.last.scan, pose=self.last.pose, particles=list(f.particles),
            weights=list(f.weights)
        )
        self._pubs["viz"].put(data)
        self.status.viz_bytes += len(data)

    # ------------------------------------------------------------------ the loop
    def step(self) -> bool:
        """Advance the simulation by one scan; False when the route has ended (or, with a live
        lidar, when no scan came meanwhile)."""
        if self.status.finished:
            return False
        t0 = time.perf_counter()
        try:
            s = next(self.steps)
        except StopIteration:
            self.status.finished = True
            if self.opts.live is None:  # a live lidar's steps end only when the agent stops
                self.say(f"route finished after {self.status.step} steps")
            return False
        if s is None:  # a live lidar had no scan ready
            return False
        self.status.step_ms = 1000.0 * (time.perf_counter() - t0)
        if self.last is None and s.true_pose is not None:
            self._check_start(s.true_pose)
        self.last = s
        self.status.step += 1
        self.status.t = float(s.t)
        best = s.filter.best
        self.status.vertices, self.status.edges = best.n_vertices, best.n_edges
        if self.opts.duration is not None and s.t >= self.opts.duration:
            self.status.finished = True
        return True

    def _check_start(self, first: Pose) -> None:
        """The map's origin must be where the robot really started: in simulation the first true
        pose is known, and a ``--start`` that disagrees with it (e.g. a heading that is not the
        route's) would rotate the whole map in the fleet frame. The true pose wins, with a
        warning when they differ by more than 1 cm or 0.01 rad."""
        s = self.opts.start
        if math.hypot(s.x - first.x, s.y - first.y) > 0.01:
            self.say(
                f"--start {s.x:.2f},{s.y:.2f} differs from where the simulation starts the robot "
                f"({first.x:.2f},{first.y:.2f}, heading {math.degrees(first.theta):.0f} deg); using the latter"  # noqa: E501
            )
        elif self.opts.heading_given and abs(math.remainder(s.theta - first.theta, math.tau)) > 0.01:
            self.say(
                f"start heading {math.degrees(s.theta):.0f} deg replaced by {math.degrees(first.theta):.0f} deg "  # noqa: E501
                f"(a simulated robot starts facing along its route)"
            )
        if not s.almost_equal(first, 1e-9, 1e-9):
            self.opts.start = first
            self._last_body = None

    def run(self, stop: Any) -> RobotStatus:
        """Run until ``stop`` (a ``threading.Event``) is set."""
        try:
            return self._run(stop)
        finally:
            if self.live_counts is not None:
                self.status.live = self.live_counts()

    def _run(self, stop: Any) -> RobotStatus:
        period = 1.0 / self.opts.rate if self.opts.rate > 0 else 0.0  # 0: a live lidar, as scans come
        pose_period = 1.0 / self.opts.pose_hz
        viz_period = 1.0 / self.opts.viz_hz if self.opts.viz_hz > 0 else math.inf
        now = time.monotonic()
        next_step, next_pose, next_viz = now, now, now + viz_period
        last_report = now
        while not stop.is_set():
            now = time.monotonic()
            if not self.status.finished and now >= next_step:
                if self.step():
                    self.publish_map()
                next_step += period
                if next_step < time.monotonic() - period:
                    next_step = time.monotonic()  # fell behind: do not burst to catch up
            now = time.monotonic()
            if now - self._last_map_put >= self.opts.heartbeat_s:
                self.publish_map(force=True)
            if now >= next_pose:
                if self.live_counts is not None:
                    self.status.live = self.live_counts()
                self.publish_pose()
                next_pose = max(next_pose + pose_period, now)
            if now >= next_viz:
                self.publish_viz()
                next_viz = max(next_viz + viz_period, now)
            if now - last_report >= 10.0:
                last_report = now
                if self.live_counts is not None:
                    self.status.live = self.live_counts()
                st = self.status
                live = ""
                if st.live is not None:
                    kept = ("scans", "odometry", "posed", "swept", "last_issue", "graph", "loops", "settled",
                            "revisits", "refined", "transforms", "mount", "sweep")
                    dropped = ", ".join(f"{k} {v}" for k, v in st.live.items() if k not in kept and v)
                    live = (f"; live lidar: {st.live['posed']} scans posed, {st.live['scans']} received"
                            + (f", {st.live['swept']} with the odometry over their sweep"
                               if st.live.get("swept") else "")
                            + (f"; beams' order {st.live['sweep']}" if st.live.get("sweep") else "")
                            + (f" ({dropped})" if dropped else "")
                            + (f"; the laser's mount {st.live['mount']}" if st.live.get("mount") else "")
                            + (" (calibrating: the first scans are mapped together)" if st.step == 0 else "")
                            + (f"; SLAM: {st.live['graph']} scans in its graph, {st.live['loops']} loops "
                               f"({st.live['settled']} settled), {st.live.get('revisits', 0)} scans on old "
                               f"nodes, {st.live.get('refined', 0)} nodes refined"
                               if st.live.get("graph") else ""))
                self.say(
                    f"step {st.step} t={st.t:.1f}s: {st.vertices} vertices, {st.edges} edges, {st.maps_sent} maps"  # noqa: E501
                    + live
                )
            wake = min(next_pose, next_viz, self._last_map_put + self.opts.heartbeat_s)
            if not self.status.finished:
                wake = min(wake, next_step)
            stop.wait(max(0.0, wake - time.monotonic()))
        return self.status


def parse_route(text: str) -> NDArray[np.float64]:
    """``X,Y;X,Y;...`` or a JSON file holding ``[[x, y], ...]`` (or ``{"route": [...]}``).

    Raises ``ValueError`` with the reason."""
    import json
    from pathlib import Path

    p = Path(text)
    if p.suffix.lower() in (".json", ".geojson") or p.is_file():
        try:
            doc = json.loads(p.read_text())
        except OSError as exc:
            raise ValueError(f"{text}: {exc.strerror or exc}") from None
        except json.JSONDecodeError as exc:
            raise ValueError(f"{text}: not valid JSON: {exc}") from None
        if isinstance(doc, dict):
            doc = doc.get("route", doc.get("coordinates"))
        arr = np.asarray(doc, dtype=np.float64)
    else:
        try:
            arr = np.array([[float(v) for v in pt.split(",")] for pt in text.split(";") if pt.strip()])
        except ValueError:
            raise ValueError(f"route must be X,Y;X,Y;... or a JSON file, got {text!r}") from None
    if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 1 or not np.all(np.isfinite(arr)):
        raise ValueError(f"route must be a list of [x, y] points, got shape {arr.shape}")
    return arr


def start_pose_of(route: NDArray[np.float64]) -> Pose:
    """The pose at a route's first point, facing along its first leg."""
    if len(route) < 2:
        return Pose(float(route[0, 0]), float(route[0, 1]), 0.0)
    d = route[1] - route[0]
    return Pose(float(route[0, 0]), float(route[0, 1]), math.atan2(float(d[1]), float(d[0])))


__all__ = [
    "DEFAULT_RESOLUTION", "DEFAULT_THRESHOLD", "RobotAgent", "RobotOptions", "RobotStatus", "map_message",
    "parse_route", "robot_map_message", "robot_puts", "start_pose_of",
]
