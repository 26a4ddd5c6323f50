"""A robot's own lidar, live: ROS 2 ``LaserScan`` and ``Odometry`` messages over Zenoh
(``wiremap robot --id ID --scan-key KEY --odom-key KEY``).

How a ROS 2 robot's topics reach Zenoh
--------------------------------------
* **zenoh-bridge-ros2dds** (the Zenoh plugin/bridge for ROS 2 over DDS) routes each topic to
  the key of its name: ``/scan`` -> ``scan``, ``/odom`` -> ``odom`` (behind the bridge's
  namespace when one is set, e.g. ``robot1/scan``).
* **rmw_zenoh** (ROS 2's own Zenoh middleware) puts a topic on
  ``<domain>/<topic>/<type>/<type hash>``: subscribe with ``*/scan/**`` and ``*/odom/**``.

Either way a payload is the message's CDR bytes with their 4-byte encapsulation header, which
this module deserialises without a ROS install (the ``rosbags`` library's typestore, ROS 2 Humble
definitions: ``sensor_msgs/msg/LaserScan`` and ``nav_msgs/msg/Odometry`` are the same in every ROS
2 distribution). The keys are any Zenoh key expressions.

What is made of them (choices)
------------------------------
* A scan is read as :mod:`agents.files.rosbag` reads a bag's scan (bearings, no returns, the
  checks), and an odometry message as its ``Odometry`` (the pose of its child frame in its
  header's frame). Both need a stamp: a zero stamp is refused (a bag has its record time to fall
  back on; a live message has nothing).
* **Pairing**: each scan gets the odometry *interpolated at its stamp*
  (:func:`agents.files.rosbag.interpolate`), so it waits until an odometry message stamped at or
  after it has come (the two streams' callbacks may run late and in any order in a busy
  process). A scan stamped before the oldest odometry kept (``ODOM_KEEP_N`` messages, at least
  ``ODOM_KEEP_S`` seconds) is dropped (``unposed``), as is one still waiting once the odometry
  has been silent for ``max_wait`` seconds (1 s, wall clock), or once ``MAX_WAITING`` scans wait
  (odometry whose stamps never reach the scans': another clock).
* **Order**: a scan stamped at or before the previous scan is dropped (``out_of_order``); so is
  an odometry message stamped before the newest one (``out_of_order``), so the odometry stays
  sorted. After ``RESET_AFTER`` (20) such messages in a row a stream starts again from the next
  one (``resets``): a robot's clock that jumped back (its stack restarted) or a message stamped
  in the future stops the mapping for 20 messages, not for good.
* **Bounds**: an odometry pose farther than ``MAX_COORD`` (10 km) from its frame's origin, or a
  stamp whose nanoseconds are not below 1e9, is refused (``bad_odometry``, ``bad_scans``): the
  SLAM's arithmetic stays finite whatever a publisher sends.
* **The laser's mount** on the robot's base is given (``mount``, ``--laser-mount X,Y,THETA``;
  default the identity, the laser at the base's origin), or found from ``/tf_static``
  (``--tf-key KEY``, ``base_frame``, ``--base-frame``, default ``base_link``): the transforms
  from the base frame to each scan's ``frame_id``, through any chain of frames (an upside-down
  laser mirrored), as the bag reader finds them (:func:`agents.files.rosbag.mount_chain`). The
  robot subscribes with history (a latched message sent before it came, from the publisher's
  cache: zenoh-bridge-ros2dds's Advanced Pub/Sub, ``wiremap play --tf-key``); a scan waits up to
  ``max_wait`` (1 s) for transforms that reach its frame, then is dropped (``unposed``); a chain
  that puts the laser more than ``MAX_MOUNT_M`` from the base is no mount (``bad_transforms``);
  ``mount`` in the status names the chain found.
* **Time**: a scan's time is seconds since the first scan that was posed (the robot's ``t``).
  A scan whose ``time_increment`` says its beams came over time (a spinning lidar) also waits
  for the odometry past its last beam (its stamp plus the sweep, 0.2 s at most for a 5 Hz
  lidar): it is de-skewed at the wheels' velocity over its own sweep (``odom_end``;
  ``frontend.deskew``, :class:`agents.mapping_run.LiveInputs`). When that odometry does not
  come (silent for ``max_wait``), the scan goes on without it and is de-skewed at the velocity
  since the scan before, which lags the sweep by a scan.
* **Motion filter**: the mapper takes a posed scan only once the wheels have moved
  ``--min-travel`` or turned ``--min-turn`` since the last scan it took (default the profile's
  ``frontend.min_travel`` and ``min_turn``, 0.5 m and 10 degrees; ``still`` counts the others;
  :class:`agents.mapping_run.LiveInputs`). The lidar SLAM's settings were tuned on logs with a
  scan every 0.5-1 m; a live lidar sends one every few centimetres, and every scan mapped grows
  the SLAM's pose graph.
* **Backlog**: at most ``max_backlog`` posed scans wait for the mapper; beyond, the oldest is
  dropped (``behind``): a mapper that cannot keep up maps the newest scans rather than falling
  further behind.
* **Bad payloads**: one that does not deserialise, or whose fields the reader refuses, is
  counted (``bad_scans``, ``bad_odometry``), its reason kept (``last_issue``), and dropped.

Thread-safety: the Zenoh callbacks (:meth:`LiveLidar.on_scan`, :meth:`LiveLidar.on_odometry`)
and :meth:`LiveLidar.take` may run on different threads.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agents.files.carmen import LaserScan
from mapping.se2 import Pose

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"
MAX_FRAMES = 256  # frames kept from the transforms (a robot's tree has tens)
MAX_FRAME_NAME = 256  # characters of a frame name kept
ODOM_KEEP_S = 10.0
ODOM_KEEP_N = 1000
"""Odometry kept for pairing: the last ``ODOM_KEEP_N`` messages, and more while they span less
than ``ODOM_KEEP_S`` seconds of stamps (a scan whose callback runs after several odometry
callbacks, in a busy process, still finds its odometry)."""
CALIBRATION_SCANS = 30
"""A live robot's scans held for the laser's yaw and the wheels' noise (``--calibration-scans``;
the ``lidar-slam-online`` profile's 100 are for a log in hand): behind the motion filter, 30
scans are about 15 m of driving before the first map, 100 about 50 m. On the seven logs fed
one scan at a time (``tests/live_ate.py --calibration 30`` / ``100``) neither is better:
median ATE 0.510 / 0.484 m, the difference one log's loops (``docs/experiments.md``, session
25). The noise is measured again every 25 scans until it is pinned down
(:class:`mapping.lidar_frontend.OnlineSlam`)."""
MAX_MOUNT_M = 10.0  # a laser's mount farther than this from the robot's base is a typing error
MAX_WAITING = 100  # scans waiting for odometry at or after their stamp, at most
RESET_AFTER = 20
"""Messages of one stream refused in a row for their stamp (before the newest) after which that
stream starts again from the next one: a robot whose clock went back, or one message stamped in
the future, costs at most this many messages instead of stopping the mapping for good."""


@dataclass
class LiveCounts:
    """What a :class:`LiveLidar` received and what it made of it."""

    scans: int = 0
    odometry: int = 0
    posed: int = 0
    swept: int = 0  # posed scans whose beams took time, with the odometry at their last beam (de-skew)
    bad_scans: int = 0
    bad_odometry: int = 0
    unposed: int = 0
    out_of_order: int = 0
    resets: int = 0  # a stream that started again after RESET_AFTER messages in a row out of order
    behind: int = 0
    still: int = 0  # posed scans the mapper's motion filter dropped (agents.mapping_run.LiveInputs)
    transforms: int = 0  # TFMessages read (the laser's mount from the base frame: LiveLidar.base_frame)
    bad_transforms: int = 0
    mount: str = ""  # the chain of frames the laser's mount was found through ("base_link -> laser")
    # the order the beams are de-skewed in from the calibrations on ("as declared" or
    # "reversed", judged or not, on how many turning scans): agents.mapping_run.LiveInputs.sweep
    sweep: str = ""
    last_issue: str = ""
    # the online SLAM's pose graph: its nodes (scans kept for loop closure), the loops it closed,
    # how many of them were settled (mapping.lidar_slam.SlamConfig.loop_settled_xy), the
    # scans posed on an old node instead of becoming one (SlamConfig.revisit_xy), and the nodes
    # its online refinement matched again (SlamConfig.refine_online_nodes)
    graph: int = 0
    loops: int = 0
    settled: int = 0
    revisits: int = 0
    refined: int = 0

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class _Waiting:
    raw: Any  # agents.files.rosbag._RawScan
    arrived: float  # monotonic


@dataclass
class LiveLidar:
    """Live scans paired with live odometry (module notes). Feed it the payloads
    (:meth:`on_scan`, :meth:`on_odometry`: bytes, or Zenoh samples), take the posed scans
    (:meth:`take`). With ``use_transforms``, the laser's mount is not ``mount`` but the
    transforms (:meth:`on_transforms`: ``/tf_static``) from the base frame (``base_frame``, else
    the odometry's ``child_frame_id``, else ``base_link``) to each scan's ``frame_id``; a scan
    whose frame they do not reach within ``max_wait`` seconds of its coming is dropped
    (``unposed``)."""

    mount: Pose = field(default_factory=Pose)
    use_transforms: bool = False
    base_frame: str | None = None
    max_wait: float = 1.0
    max_backlog: int = 200
    clock: Callable[[], float] = time.monotonic
    counts: LiveCounts = field(default_factory=LiveCounts)

    def __post_init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        if self.base_frame is not None:
            self.base_frame = self.base_frame.lstrip("/")  # as the messages' frames are read
            if not self.base_frame:
                raise ValueError("base_frame must name a frame")
        self._odom_frame = ""  # the odometry's child frame, the robot's base by default
        self._store = get_typestore(Stores.ROS2_HUMBLE)
        self._cond = threading.Condition()
        self._odom_t: list[float] = []
        self._odom: list[Pose] = []
        self._waiting: collections.deque[_Waiting] = collections.deque()
        self._ready: collections.deque[LaserScan] = collections.deque()
        self._last_scan_t = -math.inf
        self._t0: float | None = None
        self._scan_refused = 0  # scans refused in a row for their stamp
        self._odom_arrived = -math.inf  # when the last odometry was taken (clock)
        self._odom_refused = 0
        self._links: dict[str, tuple[str, Any]] = {}  # child frame -> (parent, transform)
        self._mounts: dict[str, Any] = {}  # a scan frame's mount, once the transforms reach it

    # ------------------------------------------------------------------ the callbacks
    def _read(
        self, payload: Any, msgtype: str, stream: str, label: str, read: Callable[[Any, int], Any]
    ) -> tuple[Any, int] | None:
        """``(read(message, number), number)`` of a payload of the stream ``stream`` (its count in
        ``counts``, the message's number); None when it does not deserialise as ``msgtype`` or
        ``read`` refuses it (:class:`agents.files.rosbag.MessageError`): counted in
        ``bad_<stream>``, the reason kept, ``label`` naming the message."""
        from agents.files.rosbag import MessageError

        data = _bytes_of(payload)
        with self._cond:
            number = getattr(self.counts, stream) + 1
            setattr(self.counts, stream, number)
        try:
            return read(self._store.deserialize_cdr(data, msgtype), number), number
        except MessageError as exc:
            self._issue(f"bad_{stream}", f"{label} {number}: {exc}")
        except Exception as exc:  # what a bad buffer makes the deserialiser raise
            self._issue(f"bad_{stream}",
                        f"{label} {number}: cannot be deserialised as {msgtype} ({_one_line(exc)})")
        return None

    def on_scan(self, payload: Any) -> None:
        from agents.files.rosbag import scan_beams

        got = self._read(payload, SCAN_TYPE, "scans", "scan", lambda msg, k: scan_beams(msg, k - 1))
        if got is None:
            return
        raw, number = got
        with self._cond:
            if raw.t <= self._last_scan_t:
                self._scan_refused += 1
                if self._scan_refused < RESET_AFTER:
                    self.counts.out_of_order += 1
                    self.counts.last_issue = (f"scan {number}: stamped {raw.t:.6f}, not after the "
                                              "previous scan")
                    return
                self.counts.resets += 1  # the scans' clock went back (or one came from the future)
                self.counts.last_issue = (f"scan {number}: {RESET_AFTER} scans in a row stamped before "
                                          f"{self._last_scan_t:.6f}; the scans' clock starts again")
                self.counts.unposed += len(self._waiting)  # scans of the old clock go with it
                self._waiting.clear()
            self._scan_refused = 0
            self._last_scan_t = raw.t
            self._waiting.append(_Waiting(raw, self.clock()))
            self._pair()

    def on_odometry(self, payload: Any) -> None:
        from agents.files.rosbag import odometry_pose

        def read(msg: Any, _number: int) -> tuple[float, Pose, str]:
            t, pose = odometry_pose(msg)
            return t, pose, str(msg.child_frame_id).lstrip("/")[:MAX_FRAME_NAME]

        got = self._read(payload, ODOM_TYPE, "odometry", "odometry", read)
        if got is None:
            return
        (t, pose, child), number = got
        with self._cond:
            if self._odom_t and t < self._odom_t[-1]:
                self._odom_refused += 1
                if self._odom_refused < RESET_AFTER:
                    self.counts.out_of_order += 1
                    self.counts.last_issue = f"odometry {number}: stamped {t:.6f}, before the newest"
                    return
                self.counts.resets += 1
                self.counts.last_issue = (f"odometry {number}: {RESET_AFTER} messages in a row stamped "
                                          f"before {self._odom_t[-1]:.6f}; the odometry starts again")
                self._odom_t, self._odom = [], []
            self._odom_refused = 0
            self._odom_arrived = self.clock()
            if child and child != self._odom_frame and self.use_transforms and self.base_frame is None:
                self._odom_frame = child  # the base the mount is found from
                self._mounts.clear()
            self._odom_t.append(t)
            self._odom.append(pose)
            if len(self._odom_t) > ODOM_KEEP_N and self._odom_t[1] < t - ODOM_KEEP_S:
                del self._odom_t[0], self._odom[0]
            self._pair()

    def on_transforms(self, payload: Any) -> None:
        """A ``tf2_msgs/TFMessage`` (``/tf_static``): its transforms kept (the latest of each
        child frame, as tf2 keeps them; at most ``MAX_FRAMES`` frames, a message of more refused
        before it is read), for the laser's mount from the base frame; a transform that is not
        one is counted (``bad_transforms``) and left out, the others kept."""
        from agents.files.rosbag import transform_links

        got = self._read(payload, TF_TYPE, "transforms", "transforms",
                         lambda msg, _number: transform_links(msg, MAX_FRAMES))
        if got is None:
            return
        (links, bad), number = got
        for why in bad:
            self._issue("bad_transforms", f"transforms {number}: {why}")
        with self._cond:
            for parent, child, rigid in links:
                if child in self._links or len(self._links) < MAX_FRAMES:
                    self._links[child] = (parent, rigid)
                else:
                    self.counts.bad_transforms += 1
                    self.counts.last_issue = (f"transforms {number}: more than {MAX_FRAMES} frames; "
                                              f"{child} left out")
            self._mounts.clear()  # found again from the transforms as they are now
            self._pair()

    def _mount_of(self, frame: str) -> Any:
        """The scan frame's mount (an ``agents.files.rosbag`` mount: pose, upside-down, chain):
        None without transforms to find it from (``mount`` is used); else through the transforms
        from the base frame (``base_frame``, or the odometry's child frame, or ``base_link``),
        ``False`` while they do not reach ``frame`` or put the laser more than ``MAX_MOUNT_M``
        from the base (a refusal kept until the next transforms; lock held)."""
        from agents.files.rosbag import mount_chain

        if not self.use_transforms:
            return None
        found: Any = self._mounts.get(frame)
        if found is None:
            base = self.base_frame or self._odom_frame or "base_link"
            try:
                with np.errstate(over="ignore", invalid="ignore"):
                    found = mount_chain(self._links, base, frame)
                far = max(abs(found.pose.x), abs(found.pose.y)) > MAX_MOUNT_M
            except (ValueError, ArithmeticError):  # a chain that overflows: not a mount either
                found, far = None, True
            if far:
                found = False
                self.counts.bad_transforms += 1
                self.counts.last_issue = (f"the transforms put the laser's frame {frame!r} more than "
                                          f"{MAX_MOUNT_M:g} m from {base}: not a mount")
            elif found.chain is None and frame and frame != base:
                found = False
                self.counts.last_issue = (f"no transforms from {base} to the scans' frame {frame!r}"
                                          + (" (they do not join it)" if self._links else " yet"))
            self._mounts[frame] = found
            self.counts.mount = found.chain or base if found else ""
        return found

    def _issue(self, counter: str, text: str) -> None:
        with self._cond:
            setattr(self.counts, counter, getattr(self.counts, counter) + 1)
            self.counts.last_issue = text

    # ------------------------------------------------------------------ pairing (lock held)
    def _pair(self) -> None:
        from agents.files.rosbag import interpolate, posed_scan, sweep_end

        if not self._waiting:
            return
        now = self.clock()
        stamps = np.asarray(self._odom_t, dtype=np.float64)
        while self._waiting:
            w = self._waiting[0]
            if stamps.size and w.raw.t < stamps[0]:
                self._drop_unposed(f"scan stamped {w.raw.t:.6f} before the odometry kept "
                                   f"({stamps[0]:.6f} on)")
                continue
            try:
                robot = interpolate(stamps, self._odom, w.raw.t) if stamps.size else None
            except (ValueError, ArithmeticError) as exc:  # bounded poses make this unreachable
                self._drop_unposed(f"scan stamped {w.raw.t:.6f}: cannot be posed ({_one_line(exc)})")
                continue
            if robot is None:
                # the odometry has not passed the scan yet: wait while it keeps coming (a busy
                # process may run the two streams' callbacks late and in any order); drop the scan
                # once the odometry has been silent for max_wait, or when too many scans wait
                if why := self._stalled(w, now):
                    self._drop_unposed(f"scan stamped {w.raw.t:.6f}: {why} (odometry up to "
                                       f"{stamps[-1] if stamps.size else float('nan'):.6f})")
                    continue
                break
            end = sweep_end(w.raw)
            try:
                robot_end = None if end is None else interpolate(stamps, self._odom, end)
            except (ValueError, ArithmeticError):  # as above: de-skewed as if none came
                robot_end = None
            if end is not None and robot_end is None and not self._stalled(w, now):
                break  # a scan that took time waits for the odometry past its last beam: the de-skew's
            mount = self._mount_of(w.raw.frame)
            if mount is False:  # the transforms do not reach the scan's frame: wait for them a while
                if now - w.arrived <= self.max_wait and len(self._waiting) <= MAX_WAITING:
                    break
                self._drop_unposed(f"scan stamped {w.raw.t:.6f}: {self.counts.last_issue}")
                continue
            self._waiting.popleft()
            if self._t0 is None:
                self._t0 = w.raw.t
            pose, upside_down = (self.mount, False) if mount is None else (mount.pose, mount.upside_down)
            self._ready.append(posed_scan(w.raw, robot, pose, upside_down, t=w.raw.t - self._t0,
                                          robot_end=robot_end))
            self.counts.posed += 1
            self.counts.swept += robot_end is not None
            while len(self._ready) > self.max_backlog:
                self._ready.popleft()
                self.counts.behind += 1
            self._cond.notify_all()

    def _stalled(self, w: _Waiting, now: float) -> str:
        """Why waiting scan ``w`` waits no longer for odometry ('' while it may): the odometry
        silent for ``max_wait``, or too many scans waiting."""
        if now - w.arrived > self.max_wait and now - self._odom_arrived > self.max_wait:
            return f"no odometry for {self.max_wait:g} s"
        return f"{MAX_WAITING} scans waiting for odometry" if len(self._waiting) > MAX_WAITING else ""

    def _drop_unposed(self, why: str) -> None:
        self._waiting.popleft()
        self.counts.unposed += 1
        self.counts.last_issue = why

    # ------------------------------------------------------------------ the mapper's side
    def take(self, timeout: float) -> LaserScan | None:
        """The oldest posed scan, waiting up to ``timeout`` seconds for one; None if none came."""
        deadline = self.clock() + max(0.0, timeout)
        with self._cond:
            while True:
                self._pair()  # scans whose wait ran out go, and those behind them may be posed
                left = deadline - self.clock()
                if self._ready or left <= 0:
                    break
                self._cond.wait(min(left, 0.05))
            return self._ready.popleft() if self._ready else None

    def snapshot(self) -> dict[str, Any]:
        with self._cond:
            return self.counts.as_dict()


def _bytes_of(payload: Any) -> bytes:
    return payload.to_bytes() if hasattr(payload, "to_bytes") else bytes(payload)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 120 else text[:117] + "..."


def check_keys(scan_key: str, odom_key: str, tf_key: str | None = None) -> None:
    """``--scan-key``, ``--odom-key`` (and ``--tf-key``) as Zenoh key expressions that do not
    overlap (a message on two would be read as both); :class:`agents.errors.UserError` with the
    reason."""
    import itertools

    import zenoh

    from agents.errors import UserError

    named = [("--scan-key", scan_key, "a scan"), ("--odom-key", odom_key, "odometry")]
    if tf_key is not None:
        named.append(("--tf-key", tf_key, "transforms"))
    kes = []
    for flag, key, _ in named:
        try:
            kes.append(zenoh.KeyExpr(key))
        except Exception as exc:  # zenoh's own error type for a malformed key expression
            raise UserError(f"{flag} {key!r} is not a Zenoh key expression ({exc})") from None
    for (a, ka), (b, kb) in itertools.combinations(zip(named, kes, strict=True), 2):
        if ka.intersects(kb):
            raise UserError(f"{a[0]} {a[1]} and {b[0]} {b[1]} overlap: a message on both would be read as "
                            f"{a[2]} and as {b[2]}; give keys that do not")


def parse_mount(text: str) -> Pose:
    """``X,Y[,THETA]`` (metres, radians) as a pose; ``ValueError`` with the reason."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--laser-mount must be X,Y[,THETA] (metres, radians), got {text!r}") from None
    if len(vals) not in (2, 3) or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"--laser-mount must be X,Y[,THETA] (metres, radians), got {text!r}")
    if max(abs(vals[0]), abs(vals[1])) > MAX_MOUNT_M:
        raise ValueError(f"--laser-mount {text}: a laser more than {MAX_MOUNT_M:g} m from the robot's base")
    return Pose(vals[0], vals[1], vals[2] if len(vals) == 3 else 0.0)


def live_profile(opts: Any) -> tuple[dict[str, Any], Any, Any]:
    """``(filter overrides, ExtractConfig, FrontendConfig)`` of the robot's lidar profile, its
    scans held for the calibrations ``opts.extra["calibration_scans"]`` when given, else
    :data:`CALIBRATION_SCANS`, its beams de-skewed the other way round with
    ``opts.extra["sweep_reversed"]`` (``--reversed-sweep``; :func:`agents.mapping_run.split_profile`)."""
    from agents import mapping_run as mr

    prof = mr.lidar_profile(opts.lidar_profile)
    prof["frontend.calibration_scans"] = int(opts.extra.get("calibration_scans", CALIBRATION_SCANS))
    if opts.extra.get("sweep_reversed"):
        prof["frontend.sweep_reversed"] = True
    return mr.split_profile(prof)


def live_filter(first: Any, particles: int, threshold: float, seed: int,
                overrides: dict[str, Any]) -> tuple[Any, float]:
    """The live mapper's filter (:class:`mapping.filter.WireframeFilter`, in the robot's own
    frame: its first pose the identity) set from the first scan that comes: its field of view,
    and its range capped at :data:`agents.fleet.carmen_fleet.MAX_RANGE` (20 m, as ``wiremap map
    --carmen`` caps it); with the cap, which :class:`agents.mapping_run.LiveInputs` takes too."""
    from agents import mapping_run as mr
    from agents.fleet.carmen_fleet import MAX_RANGE
    from mapping.filter import WireframeFilter

    cap = min(float(first.max_range), MAX_RANGE)
    cfg = mr.filter_config_for(particles, threshold, cap, fov=mr.scan_fov(first.angles), overrides=overrides)
    return WireframeFilter(cfg, mr.seeds_for(seed)["filter"], initial_pose=Pose.identity()), cap


def live_steps(opts: Any, source: LiveLidar, stop: threading.Event) -> Iterator[Any]:
    """The robot's loop over live scans: each posed scan through :class:`agents.mapping_run.LiveInputs`
    (profile ``opts.lidar_profile``, which must run its SLAM scan by scan) and the filter, one
    :class:`agents.mapping_run.RunStep` per scan mapped; None when a scan mapped nothing (held for
    the calibration, left out by the motion filter) or none came within 0.05 s, so that the
    agent keeps publishing its pose and heartbeats meanwhile; ends when ``stop`` is set. The
    filter's field of view and range come from the first scan (the range capped at 20 m, as
    ``wiremap map --carmen`` caps it). The first ``frontend.calibration_scans`` scans
    (:func:`live_profile`) are mapped together once the last of them has come
    (:class:`agents.mapping_run.LiveInputs`)."""
    from dataclasses import replace

    from agents import mapping_run as mr
    from agents.fleet.carmen_fleet import MAX_RANGE
    from mapping.filter import WireframeFilter

    settings, extract, frontend = live_profile(opts)
    inputs = mr.LiveInputs(max_range=MAX_RANGE, extract=extract, frontend=frontend,
                           min_travel=float(opts.extra.get("min_travel", frontend.min_travel)),
                           min_turn=float(opts.extra.get("min_turn", frontend.min_turn)))
    filt: WireframeFilter | None = None
    k = 0
    while not stop.is_set():
        ls = source.take(0.05)
        if ls is None:
            yield None
            continue
        if filt is None:
            overrides = {**settings, **(opts.filter_overrides or {})}
            filt, inputs.max_range = live_filter(ls, int(opts.particles), float(opts.threshold),
                                                 int(opts.seed), overrides)
        ready = inputs.add(ls)
        source.counts.still = inputs.skipped
        if inputs.sweep is not None and not source.counts.sweep:
            judged = inputs.sweep
            order = "reversed" if judged.reversed else "as declared"
            how = "not judged" if math.isnan(judged.gain) else "judged"
            source.counts.sweep = f"{order}, {how} ({judged.scans} turning scans)"
        slam = inputs.slam
        if slam is not None:
            source.counts.graph, source.counts.loops = len(slam.poses), len(slam.loops)
            source.counts.settled, source.counts.revisits = slam.settled, slam.skipped
            source.counts.refined = slam.refined
        if not ready:  # held for the calibration, or left out by the motion filter
            yield None
            continue
        for step in mr.run_filter(ready, filt):
            yield replace(step, index=k)
            k += 1
