"""Every Rerun call of the project lives here: one small adapter, :class:`FleetRecorder`.

Entity tree (all coordinates in the fleet frame, metres)::

    world/truth                         the true walls (static), when the world is known
    robots/<id>/true_pose               where the simulator says the robot is
    robots/<id>/pose                    the robot's estimate (start pose * odometry estimate)
    robots/<id>/scan                    the current scan, placed at the estimated pose
    robots/<id>/particles               every particle's wireframe, faded
    robots/<id>/map                     the robot's best wireframe (grey while it is stale)
    robots/<id>/trajectory              the estimated path so far, a line (every 5 cm, sent at most
                                        once a second)
    robots/<id>/status                  "joined" / "stale" / "alive again" text entries
    fused/walls                         fused walls, coloured by contributing robot(s)
    fused/corners/{nominal,occlusion,frontier}
                                        circles, triangles and squares (the paper's Fig. 2)
    stats/fused/{vertices,edges}, stats/latency_ms, stats/robots/<id>/edges,
    stats/robots/<id>/alive             time series (alive: 1 while the robot's token lives, 0 stale),
                                        a sample a second for every robot seen
    log                                 text events: robots joining, going stale, coming back;
                                        dropped payloads

Timelines: ``fleet_time`` (seconds since the recording started, by the recorder's clock: one
clock for every robot, so a robot started later appears later) and ``sim_time`` (the
robots' simulated seconds, each robot's own clock from its start; the fused map's is the
latest). The blueprint opens on ``fleet_time`` with the fleet view, one view per robot, the
time series and the event log. A file sink always; optionally a gRPC
server sink that a viewer attaches to later (``rerun --connect
rerun+http://127.0.0.1:PORT/proxy``). The algorithm never imports this module.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.files.render import ROBOT_COLORS
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

# A qualitative palette (RGB), robot k gets PALETTE[k % len(PALETTE)] (the pictures' colours).
PALETTE: tuple[tuple[int, int, int], ...] = ROBOT_COLORS
#: Seconds between two sends of a robot's trajectory line and of the ``alive`` samples.
TRACK_EVERY_S = 1.0
STALE_COLOUR = (150, 150, 150)
LABEL_COLOURS = {
    Label.NOMINAL: (220, 30, 30),
    Label.OCCLUSION: (250, 160, 0),
    Label.FRONTIER: (40, 120, 255),
}


def robot_colour(index: int) -> tuple[int, int, int]:
    return PALETTE[int(index) % len(PALETTE)]


def mask_colours(sources: NDArray[Any], n_robots: int) -> NDArray[np.uint8]:
    """One RGB colour per edge: a single contributor's colour, or the mean of several (masks
    of any width: ``uint64`` or Python ints, ``mapping.wireframe.as_masks``)."""
    out = np.full((len(sources), 3), 200, dtype=np.uint8)
    for e, mask in enumerate(np.asarray(sources).tolist()):
        ks = [k for k in range(n_robots) if (int(mask) >> k) & 1]
        if ks:
            out[e] = np.mean([robot_colour(k) for k in ks], axis=0).astype(np.uint8)
    return out


def _strips(wf: Wireframe) -> NDArray[np.float64]:
    return wf.segments() if wf.n_edges else np.zeros((0, 2, 2))


class FleetRecorder:
    """Logs the fleet to a ``.rrd`` file (and optionally a live viewer port).

    Parameters
    ----------
    path : the recording file; its directory is created.
    serve_port : also serve the stream on ``127.0.0.1:serve_port`` for a viewer.
    recording_id : processes sharing it (and the application id) make one recording.
    """

    def __init__(
        self,
        path: str | Path,
        serve_port: int | None = None,
        recording_id: str | None = None,
        application_id: str = "wiremap",
    ) -> None:
        import rerun as rr

        self._rr = rr
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id or str(uuid.uuid4()))
        sinks: list[object] = [rr.FileSink(str(path))]
        if serve_port is not None:
            sinks.append(rr.GrpcServerSink(bind_ip="127.0.0.1", port=int(serve_port)))
        self.rec.set_sinks(*sinks)  # type: ignore[arg-type]
        self.robots: list[str] = []
        self._blueprint_robots: tuple[str, ...] | None = None
        self._t0 = time.monotonic()
        self._tracks: dict[str, list[tuple[float, float]]] = {}
        self._track_sent: dict[str, float] = {}
        self._stale: set[str] = set()
        self._alive_sent = -1.0
        #: where log_fused draws: ``fused`` (the fleet's map); a regional fuser of a fusion tree
        #: draws its partial map under ``groups/<NAME>`` (the root draws ``fused``)
        self.fused_path = "fused"
        self.send_blueprint()

    def fleet_time(self) -> float:
        """Seconds since the recording started (the ``fleet_time`` timeline)."""
        return time.monotonic() - self._t0

    # ------------------------------------------------------------------ layout
    def robot_index(self, robot: str) -> int:
        if robot not in self.robots:
            self.robots.append(robot)
            self.robots.sort()
            text = f"{robot} joined"
            self.rec.set_time("fleet_time", duration=self.fleet_time())
            self.rec.log(f"robots/{robot}/status", self._rr.TextLog(text, level="INFO"))
            self.rec.log("log", self._rr.TextLog(text, level="INFO"))
            self.rec.log(f"stats/robots/{robot}/alive", self._rr.Scalars([1.0]))
        return self.robots.index(robot)

    def send_blueprint(self) -> None:
        """Fleet view on the left (truth, fused map, poses, scans); one view per robot and the
        time series on the right. Re-sent when a robot appears."""
        import rerun.blueprint as rrb

        robots = tuple(self.robots)
        if robots == self._blueprint_robots:
            return
        self._blueprint_robots = robots
        per_robot = [
            rrb.Spatial2DView(
                name=f"robot {r}",
                origin="/",
                contents=["world/truth", f"robots/{r}/**"],
            )
            for r in robots
        ]
        right: list[object] = []
        if per_robot:
            right.append(rrb.Grid(*per_robot))
        right.append(rrb.TimeSeriesView(name="stats", origin="stats"))
        right.append(rrb.TextLogView(name="events", origin="log"))
        bp = rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial2DView(
                    name="fleet",
                    origin="/",
                    contents=[
                        "world/truth",
                        "fused/**",
                        "robots/*/true_pose",
                        "robots/*/pose",
                        "robots/*/scan",
                        "robots/*/trajectory",
                    ],
                ),
                rrb.Vertical(*right),  # type: ignore[arg-type]
                column_shares=[3, 2],
            ),
            rrb.TimePanel(timeline="fleet_time", expanded=True),
            collapse_panels=False,
        )
        self.rec.send_blueprint(bp)

    def set_time(self, t: float) -> None:
        """Both clocks: ``sim_time`` = ``t`` (simulated seconds), ``fleet_time`` = now."""
        self.rec.set_time("sim_time", duration=float(max(t, 0.0)))
        self.rec.set_time("fleet_time", duration=self.fleet_time())

    # ------------------------------------------------------------------ world
    def log_truth(self, truth: Wireframe) -> None:
        rr = self._rr
        self.rec.log(
            "world/truth",
            rr.LineStrips2D(_strips(truth), colors=[(90, 90, 90)], radii=[0.03], draw_order=1.0),
            static=True,
        )

    # ------------------------------------------------------------------ robots
    def log_robot_pose(self, robot: str, t: float, estimate: Pose, truth: Pose | None) -> None:
        """Poses in the fleet frame: the estimate as an arrow, the truth (if known) as a ring."""
        rr = self._rr
        k = self.robot_index(robot)
        self.send_blueprint()
        self.set_time(t)
        c = robot_colour(k)
        d = 0.5 * np.array([np.cos(estimate.theta), np.sin(estimate.theta)])
        self.rec.log(
            f"robots/{robot}/pose",
            rr.Arrows2D(
                origins=[[estimate.x, estimate.y]],
                vectors=[d],
                colors=[c],
                radii=[0.05],
                labels=[robot],
                draw_order=30.0,
            ),
        )
        track = self._tracks.setdefault(robot, [])
        if not track or np.hypot(estimate.x - track[-1][0], estimate.y - track[-1][1]) >= 0.05:
            track.append((estimate.x, estimate.y))
        now = self.fleet_time()
        if now - self._track_sent.get(robot, -TRACK_EVERY_S) >= TRACK_EVERY_S:
            self._log_track(robot)
        if now - self._alive_sent >= TRACK_EVERY_S:  # every robot's alive series, once a second
            self._alive_sent = now
            for r in self.robots:
                self.rec.log(f"stats/robots/{r}/alive", rr.Scalars([0.0 if r in self._stale else 1.0]))
        if truth is not None:
            dt = 0.4 * np.array([np.cos(truth.theta), np.sin(truth.theta)])
            self.rec.log(
                f"robots/{robot}/true_pose",
                rr.Arrows2D(
                    origins=[[truth.x, truth.y]],
                    vectors=[dt],
                    colors=[(0, 0, 0)],
                    radii=[0.03],
                    draw_order=29.0,
                ),
            )

    def _log_track(self, robot: str) -> None:
        track = self._tracks.get(robot)
        if not track or len(track) < 2:
            return
        self._track_sent[robot] = self.fleet_time()
        c = robot_colour(self.robot_index(robot))
        self.rec.log(
            f"robots/{robot}/trajectory",
            self._rr.LineStrips2D([np.asarray(track)], colors=[c], radii=[0.025], labels=[robot],
                                  draw_order=8.0),
        )

    def log_robot_viz(
        self,
        robot: str,
        t: float,
        origin: Pose,
        pose: Pose,
        scan: Wireframe,
        particles: Sequence[Wireframe],
        weights: Sequence[float],
    ) -> None:
        """The current scan (robot frame, placed at ``origin * pose``) and the particles
        (odometry frame, placed at ``origin``), faded; the heaviest particle a bit stronger."""
        rr = self._rr
        k = self.robot_index(robot)
        self.set_time(t)
        c = robot_colour(k)
        at = origin.compose(pose)
        scan_f = scan.transformed(at)
        self.rec.log(
            f"robots/{robot}/scan",
            rr.LineStrips2D(_strips(scan_f), colors=[(*c, 255)], radii=[0.02], draw_order=20.0),
        )
        strips: list[NDArray[np.float64]] = []
        colours: list[tuple[int, int, int, int]] = []
        w = np.asarray(weights, dtype=np.float64)
        best = int(np.argmax(w)) if len(w) else -1
        for i, p in enumerate(particles):
            segs = _strips(p.transformed(origin))
            strips.extend(segs)
            alpha = 110 if i == best else 35
            colours.extend([(*c, alpha)] * len(segs))
        self.rec.log(
            f"robots/{robot}/particles",
            rr.LineStrips2D(
                np.asarray(strips).reshape(-1, 2, 2),
                colors=np.asarray(colours, dtype=np.uint8).reshape(-1, 4),
                radii=[0.015],
                draw_order=5.0,
            ),
        )

    def log_robot_map(self, robot: str, t: float, wf_fleet: Wireframe) -> None:
        """A robot's best map, already in the fleet frame."""
        rr = self._rr
        k = self.robot_index(robot)
        self.send_blueprint()
        self.set_time(t)
        c = robot_colour(k)
        self.rec.log(
            f"robots/{robot}/map",
            rr.LineStrips2D(_strips(wf_fleet), colors=[c], radii=[0.035], draw_order=10.0),
        )
        self.rec.log(f"stats/robots/{robot}/edges", rr.Scalars([float(wf_fleet.n_edges)]))

    def log_robot_status(self, robot: str, t: float, stale: bool, wf_fleet: Wireframe | None = None) -> None:
        """A robot became stale (its liveliness token went; its last map is kept) or came back:
        a text entry under ``robots/<id>/status`` and in ``log``, the ``alive`` series, and its
        map re-drawn grey while stale (in its colour again when back)."""
        rr = self._rr
        k = self.robot_index(robot)
        self.set_time(t)
        if stale:
            self._stale.add(robot)
        else:
            self._stale.discard(robot)
        text = f"{robot} stale: liveliness token gone, last map kept" if stale else f"{robot} alive again"
        level = "WARN" if stale else "INFO"
        self.rec.log(f"robots/{robot}/status", rr.TextLog(text, level=level))
        self.rec.log("log", rr.TextLog(text, level=level))
        self.rec.log(f"stats/robots/{robot}/alive", rr.Scalars([0.0 if stale else 1.0]))
        if wf_fleet is not None:
            c = STALE_COLOUR if stale else robot_colour(k)
            self.rec.log(
                f"robots/{robot}/map",
                rr.LineStrips2D(_strips(wf_fleet), colors=[c], radii=[0.035], draw_order=10.0),
            )

    # ------------------------------------------------------------------ fused
    def log_fused(
        self, t: float, wf: Wireframe, robots: Sequence[str], version: int, latency_ms: float | None = None
    ) -> None:
        """The fused map: walls coloured by contributor (bit k of ``sources`` is ``robots[k]``;
        the colour is that robot's, the mean colour when several contributed; the label lists
        them), corners by label in colour and shape (nominal red circles, occlusion orange
        triangles, frontier blue squares)."""
        rr = self._rr
        for r in robots:
            self.robot_index(r)
        self.send_blueprint()
        self.set_time(t)
        # colours follow the recorder's robot order so a robot keeps its colour everywhere
        idx = [self.robot_index(r) for r in robots]
        cols = np.full((wf.n_edges, 3), 200, dtype=np.uint8)
        names: list[str] = []
        for e, mask in enumerate(wf.sources.tolist()):
            ks = [j for j in range(len(robots)) if (int(mask) >> j) & 1]
            if ks:
                cols[e] = np.mean([robot_colour(idx[j]) for j in ks], axis=0).astype(np.uint8)
            names.append("+".join(robots[j] for j in ks))
        self.rec.log(
            f"{self.fused_path}/walls",
            rr.LineStrips2D(
                _strips(wf), colors=cols, radii=[0.05], labels=names, show_labels=False, draw_order=15.0
            ),
        )
        pts = wf.points
        nom = pts[wf.labels == Label.NOMINAL]
        self.rec.log(
            f"{self.fused_path}/corners/nominal",
            rr.Points2D(nom, colors=[LABEL_COLOURS[Label.NOMINAL]], radii=[0.09], draw_order=25.0),
        )
        occ = pts[wf.labels == Label.OCCLUSION]
        rad = 0.14
        tri = np.array([[0.0, rad], [-0.87 * rad, -0.5 * rad], [0.87 * rad, -0.5 * rad], [0.0, rad]])
        self.rec.log(
            f"{self.fused_path}/corners/occlusion",
            rr.LineStrips2D(
                [p + tri for p in occ] if len(occ) else np.zeros((0, 2, 2)),
                colors=[LABEL_COLOURS[Label.OCCLUSION]],
                radii=[0.03],
                draw_order=26.0,
            ),
        )
        fro = pts[wf.labels == Label.FRONTIER]
        self.rec.log(
            f"{self.fused_path}/corners/frontier",
            rr.Boxes2D(
                centers=fro.reshape(-1, 2),
                half_sizes=np.full((len(fro), 2), 0.1),
                colors=[LABEL_COLOURS[Label.FRONTIER]],
                radii=[0.03],
                draw_order=27.0,
            ),
        )
        self.rec.log(f"stats/{self.fused_path}/vertices", rr.Scalars([float(wf.n_vertices)]))
        self.rec.log(f"stats/{self.fused_path}/edges", rr.Scalars([float(wf.n_edges)]))
        self.rec.log(f"stats/{self.fused_path}/version", rr.Scalars([float(version)]))
        if latency_ms is not None and self.fused_path == "fused":
            self.rec.log("stats/latency_ms", rr.Scalars([float(latency_ms)]))

    # ------------------------------------------------------------------ unknown start poses
    def log_registration(
        self, t: float, line: str, a: str, b: str, accepted: bool, confidence: float, support: float
    ) -> None:
        """A registration attempt (component ``b`` onto ``a``): a text entry under
        ``registrations`` and in ``log``, its confidence and supporting wall length as series."""
        rr = self._rr
        self.set_time(t)
        level = "INFO" if accepted else "DEBUG"
        self.rec.log("registrations", rr.TextLog(line, level=level))
        self.rec.log("log", rr.TextLog(line, level=level))
        self.rec.log(f"stats/registration/{b}/confidence", rr.Scalars([float(confidence)]))
        self.rec.log(f"stats/registration/{b}/support_m", rr.Scalars([float(support)]))

    def log_island(self, t: float, root: str, members: Sequence[str], wf: Wireframe | None) -> None:
        """An island's map in its root robot's frame (drawn under ``islands/<root>``, apart
        from the fleet frame: its place in it is unknown); ``wf`` None clears it (it joined)."""
        rr = self._rr
        self.set_time(t)
        if wf is None:
            self.rec.log(f"islands/{root}", rr.Clear(recursive=True))
            return
        c = robot_colour(self.robot_index(root))
        self.rec.log(
            f"islands/{root}/map",
            rr.LineStrips2D(_strips(wf), colors=[c], radii=[0.035], labels=["+".join(members)],
                            draw_order=10.0),
        )

    def log_quarantine(self, robot: str, t: float, text: str, wf_fleet: Wireframe) -> None:
        """A robot map kept aside as inconsistent (not merged): drawn red under
        ``quarantine/<robot>/map`` (the latest one), the reason in ``quarantine/<robot>/reason``
        and in ``log``."""
        rr = self._rr
        self.set_time(t)
        self.rec.log(
            f"quarantine/{robot}/map",
            rr.LineStrips2D(_strips(wf_fleet), colors=[(230, 40, 40)], radii=[0.05], draw_order=20.0),
        )
        line = f"{robot} quarantined: {text}"
        self.rec.log(f"quarantine/{robot}/reason", rr.TextLog(line, level="WARN"))
        self.rec.log("log", rr.TextLog(line, level="WARN"))

    def log_text(self, t: float, text: str, level: str = "INFO") -> None:
        rr = self._rr
        self.set_time(t)
        self.rec.log("log", rr.TextLog(text, level=level))

    # ------------------------------------------------------------------ end
    def flush(self, timeout: float = 5.0) -> None:
        self.rec.flush(timeout_sec=timeout)

    def close(self) -> None:
        """Send the trajectories' last points, flush and detach the sinks (the file gets its
        footer)."""
        try:
            for robot in list(self._tracks):
                self._log_track(robot)
        except Exception:  # a closing recorder never raises
            pass
        try:
            self.rec.flush(timeout_sec=5.0)
        finally:
            try:
                self.rec.disconnect()
            except Exception:
                pass


def read_recording(path: str | Path) -> tuple[set[str], set[str]]:
    """Entity paths and timeline names in a ``.rrd`` file (for tests and ``wiremap run``)."""
    from rerun.chunk import RrdReader

    entities: set[str] = set()
    timelines: set[str] = set()
    reader = RrdReader(str(path))
    for c in reader.stream().to_chunks():
        entities.add(str(c.entity_path))
        timelines.update(str(t) for t in c.timeline_names)
    return entities, timelines
