"""ROS bags: read 2D laser scans with odometry from ROS 1 and ROS 2 recordings.

Most real 2D lidar data is recorded as ROS bags. This module reads them without a ROS install
(through the ``rosbags`` library) into the scans the CARMEN reader gives
(:class:`agents.files.carmen.LaserScan`), so that ``wiremap map --rosbag`` maps a bag as
``wiremap map --carmen`` maps a log.

What is read
------------
A ROS 1 ``.bag`` file; a ROS 2 bag folder (``metadata.yaml`` beside ``.db3`` or ``.mcap``
files); a ``.db3`` or ``.mcap`` file, read through its folder when a ``metadata.yaml`` sits
beside it (compression, split files), else alone; a folder without ``metadata.yaml`` that holds
a single ``.db3`` or ``.mcap`` file. Message definitions come from the bag; a ROS 2 file that
carries none is read with the standard (Humble) definitions.

Topics
------
``sensor_msgs/LaserScan``
    The scans: the topic asked for, else the bag's only ``LaserScan`` topic. Each message is one
    scan: bearings ``angle_min + k * angle_increment``, time the header stamp (the bag's record
    time when the stamp is zero), readings that are not finite, zero, below ``range_min`` or at
    or beyond ``range_max`` are *no return* (``inf``), ``range_max`` is the scan's
    ``max_range``. A scanner whose increment is negative is read in increasing bearing order.
``nav_msgs/Odometry``
    The odometry: the topic asked for, else the bag's only ``Odometry`` topic (the truth topic
    aside), else ``/tf``. The message's pose is that of its ``child_frame_id`` (the robot's
    base) in its header's frame.
``tf2_msgs/TFMessage`` on ``/tf``
    Odometry without an ``Odometry`` topic: the transforms from ``odom_frame`` to
    ``base_frame`` (``odom`` and ``base_link`` by default), at their header stamps.
``/tf_static`` (and fixed transforms on ``/tf``)
    The laser's mounting offset on the robot: the chain of transforms from the robot's base
    frame to the scans' ``frame_id``, the first transform of each frame pair, ``/tf_static``
    before ``/tf``. Without one the laser sits at the base's origin (``mount`` is the identity).
    3D transforms are projected on the plane: the laser's heading is that of its x axis; a
    laser mounted upside down (its z axis pointing down) has its bearings mirrored.
A truth topic (``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` or
``geometry_msgs/PoseWithCovarianceStamped``), only when asked for
    The robot's true pose (a simulator's ground truth), kept per scan in :attr:`RosBag.truth`.

Poses are planar: ``x``, ``y`` and the heading of the x axis of a 3D orientation.

Odometry at a scan's time
-------------------------
The odometry (and the truth) is interpolated at each scan's stamp: linearly in ``x`` and
``y``, along the shorter turn in heading; a stamp equal to a sample's takes that sample as it
is. A scan stamped before the first or after the last odometry sample (or truth sample) has no
pose and is skipped; :attr:`RosBag.unposed` counts them.

Unreadable messages
-------------------
A message that cannot be deserialised, or a scan whose fields disagree (more than one beam
between the number of ranges and ``angle_min .. angle_max`` by ``angle_increment``; a bearing
field, ``range_max`` or ``range_min`` that is not finite; no ranges; a zero increment), or an
odometry, truth or transform message whose pose is not finite is an *issue* naming the bag, the
topic and the message's 1-based number on it (``run.bag: /scan message 12: ...``). With
``strict=True`` the first issue raises :class:`RosbagError`; otherwise the message is skipped
and the issue kept in :attr:`RosBag.issues`. A skipped scan still counts in
:attr:`LaserScan.index`.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.errors import UserError
from agents.files.carmen import LaserScan, beam_time_increment, sweep_seconds
from mapping.se2 import Pose, wrap_angle

FloatArray = NDArray[np.float64]

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"
POSE_STAMPED_TYPE = "geometry_msgs/msg/PoseStamped"
POSE_COV_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
#: Message types a truth topic may have.
TRUTH_TYPES = (ODOM_TYPE, POSE_STAMPED_TYPE, POSE_COV_TYPE)
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
DEFAULT_ODOM_FRAME = "odom"
DEFAULT_BASE_FRAME = "base_link"
#: The kind of every scan read from a bag (:attr:`LaserScan.kind`).
SCAN_KIND = "LaserScan"
MAX_CHAIN = 32  # frames followed from the laser up to the base before giving up (a cycle)
MAX_LISTED = 8  # topics or frame pairs named in one error line

__all__ = [
    "DEFAULT_BASE_FRAME",
    "DEFAULT_ODOM_FRAME",
    "RosBag",
    "RosbagError",
    "interpolate",
    "read_rosbag",
]


class RosbagError(UserError):
    """A bag that cannot be read, or a topic that cannot be chosen: the message names the bag and,
    for a bad message, its topic and number (``run.bag: /scan message 12: ...``)."""


@dataclass
class RosBag:
    """What :func:`read_rosbag` found in a bag.

    Attributes
    ----------
    path : str
        The bag as given.
    format : str
        ``"ros1"``, ``"ros2-sqlite3"`` or ``"ros2-mcap"``.
    scans : list of LaserScan
        The scans that have odometry (and truth, when asked for) at their time, in bag order;
        ``odom`` is the laser's pose (the robot's odometry composed with ``mount``).
    scan_topic : str
    odometry : str
        Where the odometry came from: its topic, or ``"/tf"``.
    odom_frames : (str, str) or None
        ``(odom frame, base frame)`` of the ``/tf`` odometry; None for an ``Odometry`` topic.
    laser_frame : str
        The first scan's ``frame_id`` (``""`` without scans).
    mount : Pose
        The laser's pose on the robot (identity when the bag has no transform to it).
    mount_from : str or None
        The transforms it came from (``"base_link -> laser"``), None for the identity.
    upside_down : bool
        The laser is mounted upside down (its bearings are mirrored).
    truth_topic : str or None
    truth : list of Pose or None
        The laser's true pose per scan (the truth topic's pose composed with ``mount``).
    messages : dict of str to int
        Messages read per topic used (unreadable ones included).
    skipped : dict of str to int
        Messages skipped as unreadable, per topic (topics with none left out).
    unposed : int
        Readable scans skipped for want of odometry (or truth) at their time.
    issues : list of str
        One message per skipped message (``path: topic message k: ...``).
    topics : dict of str to str
        Every topic of the bag and its message type.
    """

    path: str
    format: str
    scans: list[LaserScan]
    scan_topic: str
    odometry: str
    odom_frames: tuple[str, str] | None
    laser_frame: str
    mount: Pose
    mount_from: str | None
    upside_down: bool
    truth_topic: str | None
    truth: list[Pose] | None
    messages: dict[str, int]
    skipped: dict[str, int]
    unposed: int
    issues: list[str]
    topics: dict[str, str]


# ---------------------------------------------------------------------------- opening
def _one_line(exc: BaseException) -> str:
    """An exception's text on one line, cut to 200 characters."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _ros2_format(folder: Path) -> str:
    """``ros2-mcap`` or ``ros2-sqlite3`` from a bag folder's ``metadata.yaml`` (its
    ``storage_identifier``), else from its files."""
    try:
        text = (folder / "metadata.yaml").read_text(encoding="utf-8", errors="replace")
    except OSError:
        text = ""
    found = re.search(r"storage_identifier:\s*['\"]?(\w+)", text)
    if found:
        return f"ros2-{found.group(1)}"
    return "ros2-mcap" if any(folder.glob("*.mcap")) else "ros2-sqlite3"


def _locate(path: Path, where: str) -> tuple[Path, str]:
    """What to open for ``path`` (see the module notes) and the bag's format."""
    if not path.exists():
        raise RosbagError(f"{where}: no such file or directory")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return path, _ros2_format(path)
        files = sorted(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
        if len(files) == 1:
            return files[0], "ros2-mcap" if files[0].suffix == ".mcap" else "ros2-sqlite3"
        found = f"{len(files)} .db3/.mcap files" if files else "no .db3 or .mcap file"
        raise RosbagError(f"{where}: not a ROS 2 bag folder (no metadata.yaml, {found})")
    if path.suffix == ".bag":
        return path, "ros1"
    if path.suffix in (".db3", ".mcap"):
        fmt = "ros2-mcap" if path.suffix == ".mcap" else "ros2-sqlite3"
        if (path.parent / "metadata.yaml").is_file():
            return path.parent, _ros2_format(path.parent)
        return path, fmt
    raise RosbagError(f"{where}: not a ROS bag (expected a .bag, .db3 or .mcap file or a ROS 2 bag folder)")


def _open(target: Path, where: str) -> Any:
    """An open ``rosbags`` reader of ``target``; anything its readers raise on a file that is not
    a bag, or a damaged one, becomes a one-line :class:`RosbagError`."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([target], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # the readers raise what a bad file makes them raise
        raise RosbagError(f"{where}: not a readable ROS bag: {_one_line(exc)}") from None
    return reader


# ---------------------------------------------------------------------------- topics
def _listing(names: Iterable[str], topics: dict[str, str] | None = None) -> str:
    """``a, b, c`` (with their types when ``topics`` is given), at most :data:`MAX_LISTED`."""
    names = list(names)
    shown = [f"{n} ({topics[n]})" if topics is not None else n for n in names[:MAX_LISTED]]
    more = f", and {len(names) - MAX_LISTED} more" if len(names) > MAX_LISTED else ""
    return (", ".join(shown) + more) if shown else "none"


def _short(msgtype: str) -> str:
    """``sensor_msgs/LaserScan`` for ``sensor_msgs/msg/LaserScan``."""
    return msgtype.replace("/msg/", "/")


def _named(topics: dict[str, str], asked: str) -> str | None:
    """The bag's topic called ``asked``, with or without its leading slash."""
    for name in (asked, "/" + asked.lstrip("/")):
        if name in topics:
            return name
    return None


def _pick(
    topics: dict[str, str], asked: str | None, types: tuple[str, ...], flag: str, where: str,
    exclude: tuple[str | None, ...] = (),
) -> str | None:
    """The topic ``asked`` for (it must have one of ``types``), else the only topic of those
    types (``exclude`` aside); None when there is none and none was asked for."""
    what = " or ".join(_short(t) for t in types)
    if asked is not None:
        name = _named(topics, asked)
        if name is None:
            cands = sorted(n for n, t in topics.items() if t in types)
            raise RosbagError(f"{where}: {flag} {asked}: no such topic; {what} topics: {_listing(cands)}")
        if topics[name] not in types:
            raise RosbagError(f"{where}: {flag} {name} is a {_short(topics[name])}, not a {what}")
        return name
    cands = sorted(n for n, t in topics.items() if t in types and n not in exclude)
    if len(cands) > 1:
        raise RosbagError(f"{where}: {len(cands)} {what} topics ({_listing(cands)}); choose one with {flag}")
    return cands[0] if cands else None


@dataclass(frozen=True)
class _Choice:
    """The topics read: scans, odometry (an ``Odometry`` topic or ``/tf``), truth."""

    scan: str
    odom: str
    odom_is_tf: bool
    truth: str | None


def _choose(
    topics: dict[str, str], where: str, scan_topic: str | None, odom_topic: str | None,
    truth_topic: str | None,
) -> _Choice:
    """The topics to read (module notes), or a one-line :class:`RosbagError` naming the
    candidates."""
    scan = _pick(topics, scan_topic, (SCAN_TYPE,), "--scan-topic", where)
    if scan is None:
        everything = _listing(sorted(topics), topics)
        raise RosbagError(f"{where}: no sensor_msgs/LaserScan topic (topics: {everything})")
    truth = None
    if truth_topic is not None:
        truth = _pick(topics, truth_topic, TRUTH_TYPES, "--truth-topic", where)
    odom = _pick(topics, odom_topic, (ODOM_TYPE, TF_TYPE) if odom_topic is not None else (ODOM_TYPE,),
                 "--odom-topic", where, exclude=(truth,))
    if odom is not None and odom == truth:
        raise RosbagError(f"{where}: --odom-topic and --truth-topic are both {odom}")
    if odom is None:
        if topics.get(TF_TOPIC) != TF_TYPE:
            raise RosbagError(f"{where}: no odometry: no nav_msgs/Odometry topic and no {TF_TOPIC} "
                              f"(topics: {_listing(sorted(topics), topics)})")
        odom = TF_TOPIC
    return _Choice(scan, odom, topics[odom] == TF_TYPE, truth)


# ---------------------------------------------------------------------------- messages
class _Bad(Exception):
    """A message whose fields cannot be used (the text says why)."""


def _stamp(header: Any, bag_ns: int) -> float:
    """A header's stamp in seconds; the bag's record time when the stamp is zero."""
    sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
    if sec == 0 and nsec == 0:
        return bag_ns * 1e-9
    return sec + nsec * 1e-9


def _frame(name: str) -> str:
    """A frame id without its leading slash (ROS 1 bags often write ``/base_link``)."""
    return str(name).lstrip("/")


def _rotation(q: Any) -> NDArray[np.float64]:
    """The 3x3 rotation matrix of a quaternion (normalised first)."""
    v = np.array([float(q.w), float(q.x), float(q.y), float(q.z)], dtype=np.float64)
    norm = float(np.linalg.norm(v))
    if not (math.isfinite(norm) and norm > 1e-9):
        raise _Bad("orientation is not a rotation (a zero or non-finite quaternion)")
    w, x, y, z = v / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


@dataclass(frozen=True)
class _Rigid:
    """A 3D rigid transform: rotation ``r`` and translation ``t``."""

    r: NDArray[np.float64]
    t: NDArray[np.float64]

    @classmethod
    def of(cls, position: Any, orientation: Any) -> _Rigid:
        t = np.array([float(position.x), float(position.y), float(position.z)], dtype=np.float64)
        if not np.isfinite(t).all():
            raise _Bad("position is not finite")
        return cls(_rotation(orientation), t)

    def compose(self, other: _Rigid) -> _Rigid:
        return _Rigid(self.r @ other.r, self.r @ other.t + self.t)

    def planar(self) -> Pose:
        """The pose on the plane: ``x``, ``y`` and the heading of the x axis."""
        return Pose(float(self.t[0]), float(self.t[1]), math.atan2(self.r[1, 0], self.r[0, 0]))


def _planar(position: Any, orientation: Any) -> Pose:
    return _Rigid.of(position, orientation).planar()


@dataclass
class _RawScan:
    """A readable scan before its pose is known."""

    index: int
    t: float
    ranges: FloatArray  # no return already inf
    angles: FloatArray
    max_range: float
    frame: str
    time_increment: float = 0.0  # seconds from one beam to the next, in the message's order


def _raw_scan(msg: Any, index: int, bag_ns: int) -> _RawScan:
    """A ``LaserScan`` message's beams (module notes); :class:`_Bad` for fields that disagree."""
    a0, a1, inc = float(msg.angle_min), float(msg.angle_max), float(msg.angle_increment)
    rmin, rmax = float(msg.range_min), float(msg.range_max)
    for name, v in (("angle_min", a0), ("angle_max", a1), ("angle_increment", inc), ("range_min", rmin)):
        if not math.isfinite(v):
            raise _Bad(f"{name} is not finite ({v})")
    if not (math.isfinite(rmax) and rmax > 0.0):
        raise _Bad(f"range_max is not a positive number of metres ({rmax})")
    raw = np.asarray(msg.ranges, dtype=np.float64).reshape(-1)
    n = raw.size
    if n == 0:
        raise _Bad("has no ranges")
    if n > 1:
        if inc == 0.0:
            raise _Bad(f"has {n} ranges but a zero angle_increment")
        beams = (a1 - a0) / inc + 1.0
        if abs(n - beams) > 1.0 + 1e-6:
            raise _Bad(f"has {n} ranges, but angle_min {a0:g} .. angle_max {a1:g} by angle_increment "
                       f"{inc:g} is {beams:.1f} beams")
        if (n - 1) * abs(inc) > 2.0 * math.pi + abs(inc) + 1e-6:
            raise _Bad(f"its {n} beams {inc:g} rad apart span more than a full turn")
    angles = a0 + inc * np.arange(n, dtype=np.float64)
    ranges = raw.copy()
    with np.errstate(invalid="ignore"):
        ranges[~(ranges > 0.0) | (ranges < rmin) | (ranges >= rmax)] = np.inf  # nan fails every test
    dt = beam_time_increment(float(getattr(msg, "time_increment", 0.0)), n)
    return _RawScan(index, _stamp(msg.header, bag_ns), ranges, angles, rmax, _frame(msg.header.frame_id), dt)


@dataclass
class _Track:
    """Timed planar poses (odometry or truth), in the order read."""

    stamps: list[float] = field(default_factory=list)
    poses: list[Pose] = field(default_factory=list)
    frame: str = ""  # the child frame of Odometry messages (the robot's base), "" when unnamed

    def add(self, t: float, pose: Pose) -> None:
        self.stamps.append(t)
        self.poses.append(pose)

    def sorted(self) -> tuple[FloatArray, list[Pose]]:
        order = np.argsort(np.asarray(self.stamps, dtype=np.float64), kind="stable")
        return np.asarray(self.stamps, dtype=np.float64)[order], [self.poses[k] for k in order]


def interpolate(stamps: FloatArray, poses: list[Pose], t: float) -> Pose | None:
    """The pose at time ``t`` from poses at sorted ``stamps``: a sample's own pose at its stamp,
    else linear in ``x``, ``y`` and along the shorter turn in heading; None outside the stamps."""
    if not stamps.size or not (stamps[0] <= t <= stamps[-1]):
        return None
    k = int(np.searchsorted(stamps, t, side="left"))
    if stamps[k] == t:
        return poses[k]
    a, b = poses[k - 1], poses[k]
    f = (t - float(stamps[k - 1])) / (float(stamps[k]) - float(stamps[k - 1]))
    return Pose(a.x + f * (b.x - a.x), a.y + f * (b.y - a.y), a.theta + f * wrap_angle(b.theta - a.theta))


@dataclass
class _Collected:
    """What one pass over the bag's messages collects; ``issue`` keeps (or, with ``strict``,
    raises) an unreadable message."""

    where: str
    strict: bool
    choice: _Choice
    odom_frames: tuple[str, str]
    scans: list[_RawScan] = field(default_factory=list)
    odom: _Track = field(default_factory=_Track)
    truth: _Track = field(default_factory=_Track)
    static: dict[str, tuple[str, _Rigid]] = field(default_factory=dict)  # child -> (parent, transform)
    fixed: dict[str, tuple[str, _Rigid]] = field(default_factory=dict)  # the same from /tf
    tf_pairs: dict[tuple[str, str], int] = field(default_factory=dict)  # /tf (parent, child): count
    counts: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    issues: list[str] = field(default_factory=list)

    def issue(self, topic: str, number: int, why: str) -> None:
        err = RosbagError(f"{self.where}: {topic} message {number}: {why}")
        if self.strict:
            raise err
        self.skipped[topic] = self.skipped.get(topic, 0) + 1
        self.issues.append(str(err))


def _read_messages(reader: Any, log: _Collected) -> None:
    """Every message of the topics used into ``log``; a storage that fails mid-way is a
    :class:`RosbagError`."""
    choice = log.choice
    wanted = {choice.scan, choice.odom, TF_STATIC_TOPIC, TF_TOPIC}
    if choice.truth is not None:
        wanted.add(choice.truth)
    conns = [c for c in reader.connections if c.topic in wanted]
    try:
        for conn, bag_ns, data in reader.messages(connections=conns):
            number = log.counts.get(conn.topic, 0) + 1
            log.counts[conn.topic] = number
            try:
                msg = reader.deserialize(data, conn.msgtype)
            except Exception as exc:  # the deserialisers raise what a bad buffer makes them raise
                log.issue(conn.topic, number, f"cannot be deserialised ({_one_line(exc)})")
                continue
            try:
                _read_message(log, conn.topic, conn.msgtype, msg, number, bag_ns)
            except (_Bad, ValueError) as exc:  # ValueError: a Pose that is not finite
                log.issue(conn.topic, number, f"{_short(conn.msgtype)} {exc}")
    except RosbagError:
        raise
    except Exception as exc:  # a damaged chunk, page or record: what the storage's reader raises
        raise RosbagError(f"{log.where}: cannot read: {_one_line(exc)}") from None


def _read_message(log: _Collected, topic: str, msgtype: str, msg: Any, number: int, bag_ns: int) -> None:
    """One deserialised message into ``log`` (raises :class:`_Bad` or ``ValueError``)."""
    choice = log.choice
    if topic == choice.scan:
        log.scans.append(_raw_scan(msg, number - 1, bag_ns))
        return
    if topic == choice.truth:
        pose = msg.pose.pose if msgtype in (ODOM_TYPE, POSE_COV_TYPE) else msg.pose
        log.truth.add(_stamp(msg.header, bag_ns), _planar(pose.position, pose.orientation))
        return
    if topic == choice.odom and not choice.odom_is_tf:
        log.odom.add(_stamp(msg.header, bag_ns), _planar(msg.pose.pose.position, msg.pose.pose.orientation))
        log.odom.frame = log.odom.frame or _frame(msg.child_frame_id)
        return
    if msgtype != TF_TYPE:
        return
    # A transform message: odometry (the odom -> base pair on the odometry topic) or the mount.
    found: list[tuple[str, str, float, _Rigid]] = []
    for tf in msg.transforms:
        parent, child = _frame(tf.header.frame_id), _frame(tf.child_frame_id)
        tr = tf.transform
        found.append((parent, child, _stamp(tf.header, bag_ns), _Rigid.of(tr.translation, tr.rotation)))
    for parent, child, t, rigid in found:  # only once every transform of the message is readable
        if topic == TF_STATIC_TOPIC:
            log.static.setdefault(child, (parent, rigid))
            continue
        if topic == choice.odom and (parent, child) == log.odom_frames:
            log.odom.add(t, rigid.planar())
        elif topic == TF_TOPIC:
            log.fixed.setdefault(child, (parent, rigid))
        if topic == choice.odom:
            log.tf_pairs[(parent, child)] = log.tf_pairs.get((parent, child), 0) + 1


# ---------------------------------------------------------------------------- the laser's mount
@dataclass(frozen=True)
class _Mount:
    pose: Pose
    upside_down: bool
    chain: str | None  # "base_link -> laser", None: no transform found (identity)


def _mount(log: _Collected, base: str, laser: str) -> _Mount:
    """The laser's pose on the robot: the transforms from ``base`` to ``laser``, each frame's
    parent from ``/tf_static`` first, then from ``/tf``; the identity when none leads there."""
    return mount_chain({**log.fixed, **log.static}, base, laser)


def mount_chain(links: dict[str, tuple[str, _Rigid]], base: str, laser: str) -> _Mount:
    """The laser's pose on the robot: the transforms from ``base`` to ``laser`` through
    ``links`` (each frame's ``(parent, transform)``); the identity, with no ``chain``, when none
    leads there (or the frames go round in a cycle)."""
    if not laser or laser == base:
        return _Mount(Pose(), False, None)
    path = [laser]
    rigid = _Rigid(np.eye(3), np.zeros(3))
    frame = laser
    while frame != base:
        link = links.get(frame)
        if link is None or len(path) > MAX_CHAIN:
            return _Mount(Pose(), False, None)
        parent, step = link
        rigid = step.compose(rigid)  # parent <- frame, then frame <- laser
        frame = parent
        path.append(frame)
    return _Mount(rigid.planar(), bool(rigid.r[2, 2] < 0.0), " -> ".join(reversed(path)))


def _beams(raw: _RawScan, upside_down: bool) -> tuple[FloatArray, FloatArray, float]:
    """``(ranges, angles, time_increment)`` in increasing bearing order, mirrored for an
    upside-down laser (the time from one beam to the next negated when the order is turned)."""
    ranges, angles = raw.ranges, -raw.angles if upside_down else raw.angles
    if angles.size > 1 and angles[-1] < angles[0]:
        return ranges[::-1], angles[::-1], -raw.time_increment
    return ranges, angles, raw.time_increment


# ---------------------------------------------------------------------------- reading
def read_rosbag(
    path: str | os.PathLike[str],
    *,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    odom_frame: str = DEFAULT_ODOM_FRAME,
    base_frame: str = DEFAULT_BASE_FRAME,
    truth_topic: str | None = None,
    strict: bool = False,
) -> RosBag:
    """Read the laser scans of a ROS bag with their odometry (see the module notes).

    Parameters
    ----------
    path : str or path-like
        A ROS 1 ``.bag`` file, a ROS 2 bag folder, or a ``.db3`` or ``.mcap`` file.
    scan_topic : str, optional
        The ``sensor_msgs/LaserScan`` topic; default the bag's only one.
    odom_topic : str, optional
        The ``nav_msgs/Odometry`` topic, or a ``tf2_msgs/TFMessage`` topic such as ``/tf``;
        default the bag's only ``Odometry`` topic (``truth_topic`` aside), else ``/tf``.
    odom_frame, base_frame : str
        The odometry frame and the robot's base frame: odometry from ``/tf`` is the transform
        between them; the laser's mount is looked up from ``base_frame`` (an ``Odometry``
        topic's ``child_frame_id`` when it names one).
    truth_topic : str, optional
        A topic with the robot's true pose (``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``
        or ``geometry_msgs/PoseWithCovarianceStamped``).
    strict : bool
        Raise on the first unreadable message instead of skipping it.

    Returns
    -------
    RosBag

    Raises
    ------
    RosbagError
        When the path is missing or not a readable bag; when a topic asked for is missing or of
        the wrong type, or a default cannot be chosen (none, or several candidates); when the
        odometry is ``/tf`` and it has no ``odom_frame -> base_frame`` transform; with
        ``strict``, for the first unreadable message.
    """
    where = str(path)
    target, fmt = _locate(Path(path), where)
    odom_frames = (_frame(odom_frame), _frame(base_frame))
    reader = _open(target, where)
    try:
        topics = {name: info.msgtype or "" for name, info in reader.topics.items()}
        choice = _choose(topics, where, scan_topic, odom_topic, truth_topic)
        log = _Collected(where, strict, choice, odom_frames)
        _read_messages(reader, log)
    finally:
        reader.close()
    if choice.odom_is_tf and not log.odom.poses and log.scans:
        pairs = [f"{p} -> {c}" for p, c in sorted(log.tf_pairs)]
        raise RosbagError(f"{where}: {choice.odom} has no {odom_frames[0]} -> {odom_frames[1]} transform "
                          f"(it has {_listing(pairs)}); set --odom-frame and --base-frame")
    return _assemble(log, where, fmt, topics, base_frame)


# ---------------------------------------------------------------------------- one message at a time
class MessageError(ValueError):
    """A live message (:mod:`agents.fleet.live_lidar`) that cannot be used; the text says why."""


#: A live odometry pose farther than this (metres) from its frame's origin is refused.
MAX_COORD = 10_000.0


def _live_stamp(header: Any, what: str) -> None:
    sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
    if sec == 0 and nsec == 0:
        raise MessageError(f"{what} has a zero stamp")
    if not 0 <= nsec < 1_000_000_000:
        raise MessageError(f"{what} stamp has {nsec} nanoseconds (0 to 999999999)")


def transform_links(msg: Any, max_count: int) -> tuple[list[tuple[str, str, Any]], list[str]]:
    """A deserialised ``tf2_msgs/TFMessage``'s transforms as ``(parent, child, transform)`` (for
    :func:`mount_chain`), and why each one left out was (no two frames, not finite, not a
    rotation); :class:`MessageError` for a message of more than ``max_count`` transforms."""
    if len(msg.transforms) > max_count:
        raise MessageError(f"TFMessage has {len(msg.transforms)} transforms (at most {max_count} are read)")
    out, bad = [], []
    for tf in msg.transforms:
        parent, child = _frame(tf.header.frame_id), _frame(tf.child_frame_id)
        if not parent or not child or parent == child:
            bad.append(f"transform {parent!r} -> {child!r} does not join two frames")
            continue
        try:
            out.append((parent, child, _Rigid.of(tf.transform.translation, tf.transform.rotation)))
        except (_Bad, ValueError) as exc:
            bad.append(f"transform {parent} -> {child}: {exc}")
    return out, bad


def scan_beams(msg: Any, index: int) -> _RawScan:
    """A deserialised ``LaserScan`` message's beams, as a bag's scan is read (module notes),
    without a record time: a zero stamp or one whose nanoseconds are not below 1e9 is a
    :class:`MessageError`, as is every field the bag reader would refuse."""
    _live_stamp(msg.header, "LaserScan")
    try:
        return _raw_scan(msg, index, 0)
    except _Bad as exc:
        raise MessageError(f"LaserScan {exc}") from None


def odometry_pose(msg: Any) -> tuple[float, Pose]:
    """A deserialised ``nav_msgs/Odometry`` message's stamp (seconds) and planar pose (of its
    child frame, the robot's base, in its header's frame); :class:`MessageError` for a stamp as
    :func:`scan_beams` refuses it, or a pose that is not finite, not a rotation, or farther than
    :data:`MAX_COORD` from the origin."""
    _live_stamp(msg.header, "Odometry")
    try:
        pose = _planar(msg.pose.pose.position, msg.pose.pose.orientation)
    except (_Bad, ValueError) as exc:
        raise MessageError(f"Odometry {exc}") from None
    if max(abs(pose.x), abs(pose.y)) > MAX_COORD:
        raise MessageError(f"Odometry position ({pose.x:.6g}, {pose.y:.6g}) is more than {MAX_COORD:g} m "
                           "from its frame's origin")
    return _stamp(msg.header, 0), pose


def posed_scan(
    raw: _RawScan, robot: Pose, mount: Pose, upside_down: bool = False, t: float | None = None,
    robot_end: Pose | None = None,
) -> LaserScan:
    """The scan of ``raw`` taken with the robot's base at ``robot`` (its odometry at the scan's
    time) and the laser mounted at ``mount`` on it; ``t`` replaces the scan's time.
    ``robot_end``: the base's odometry at the last beam's time (:func:`sweep_end`), when known."""
    ranges, angles, dt = _beams(raw, upside_down)
    return LaserScan(raw.t if t is None else t, ranges, angles, raw.max_range, robot.compose(mount), mount,
                     SCAN_KIND, raw.index, dt, None if robot_end is None else robot_end.compose(mount))


def sweep_end(raw: _RawScan) -> float | None:
    """The stamp of ``raw``'s last beam (its stamp plus the sweep), or None when its beams are
    simultaneous: the odometry there gives the de-skew its velocity (``LaserScan.odom_end``)."""
    if not raw.time_increment or raw.ranges.size < 2:
        return None
    return raw.t + sweep_seconds(raw.time_increment, raw.ranges.size)


def _assemble(log: _Collected, where: str, fmt: str, topics: dict[str, str], base_frame: str) -> RosBag:
    """The :class:`RosBag` of what the pass collected: each scan posed by the odometry (and
    truth) at its time, through the laser's mount."""
    choice = log.choice
    base = log.odom.frame if (log.odom.frame and not choice.odom_is_tf) else _frame(base_frame)
    laser = log.scans[0].frame if log.scans else ""
    mounts: dict[str, _Mount] = {}
    odom_t, odom_poses = log.odom.sorted()
    truth_t, truth_poses = log.truth.sorted()
    scans: list[LaserScan] = []
    truth: list[Pose] = []
    unposed = 0
    for raw in log.scans:
        mount = mounts.get(raw.frame) or mounts.setdefault(raw.frame, _mount(log, base, raw.frame))
        robot = interpolate(odom_t, odom_poses, raw.t)
        true_robot = interpolate(truth_t, truth_poses, raw.t) if choice.truth is not None else None
        if robot is None or (choice.truth is not None and true_robot is None):
            unposed += 1
            continue
        end = sweep_end(raw)
        robot_end = None if end is None else interpolate(odom_t, odom_poses, end)
        scans.append(posed_scan(raw, robot, mount.pose, mount.upside_down, robot_end=robot_end))
        if true_robot is not None:
            truth.append(true_robot.compose(mount.pose))
    first = mounts.get(laser) or _Mount(Pose(), False, None)
    return RosBag(
        path=where,
        format=fmt,
        scans=scans,
        scan_topic=choice.scan,
        odometry=choice.odom,
        odom_frames=log.odom_frames if choice.odom_is_tf else None,
        laser_frame=laser,
        mount=first.pose,
        mount_from=first.chain,
        upside_down=first.upside_down,
        truth_topic=choice.truth,
        truth=truth if choice.truth is not None else None,
        messages={t: log.counts.get(t, 0) for t in (choice.scan, choice.odom, choice.truth) if t is not None},
        skipped=dict(log.skipped),
        unposed=unposed,
        issues=log.issues,
        topics=topics,
    )
