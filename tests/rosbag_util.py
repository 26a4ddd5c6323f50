"""ROS bags written for the tests with the ``rosbags`` writers: a ROS 1 ``.bag`` or a ROS 2 bag
folder (sqlite3 or mcap storage), message by message (:class:`BagWriter`), or the scans of a CARMEN
log with their odometry and truth (:func:`write_scans_bag`).

Independent of :mod:`agents.files.rosbag` on purpose: quaternions are written from the heading
here (``z = sin(theta / 2)``, ``w = cos(theta / 2)``), beams as ``angle_min`` and a constant
increment, so that a reader which got a convention wrong disagrees with these bags.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from agents.files.carmen import LaserScan
from mapping.se2 import Pose

#: Formats a test bag can have, and the name each is written under.
FORMATS = {"ros1": "run.bag", "sqlite3": "run-sqlite3", "mcap": "run-mcap"}
LASER_FRAME = "laser"


def stamp_of(t: float) -> tuple[int, int]:
    """``(sec, nanosec)`` of a time in seconds."""
    sec = math.floor(t)
    nsec = round((t - sec) * 1e9)
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return int(sec), int(nsec)


class MessageMaker:
    """Messages of a ROS distribution (ROS 1 Noetic, else ROS 2 Humble) built from plain values,
    and their bytes (ROS 1 serialisation, else CDR: what a ROS 2 robot puts on Zenoh)."""

    def __init__(self, ros1: bool = False) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.ros1 = ros1
        self.store = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:  # the Noetic store lacks tf2_msgs; its definition as a ROS 1 bag carries it
            self.store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                   "tf2_msgs/msg/TFMessage"))
        self.seq = 0

    def serialize(self, msg: Any) -> bytes:
        fn = self.store.serialize_ros1 if self.ros1 else self.store.serialize_cdr
        return bytes(fn(msg, msg.__msgtype__))

    # ------------------------------------------------------------------ messages
    def header(self, t: float, frame: str) -> Any:
        types = self.store.types
        sec, nsec = stamp_of(t)
        stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        if self.ros1:
            self.seq += 1
            return types["std_msgs/msg/Header"](seq=self.seq, stamp=stamp, frame_id=frame)
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def scan(
        self, t: float, ranges: Any, angle_min: float, angle_increment: float, *,
        angle_max: float | None = None, range_min: float = 0.0, range_max: float = 30.0,
        frame: str = LASER_FRAME, time_increment: float = 0.0,
    ) -> Any:
        """A ``sensor_msgs/LaserScan`` (``angle_max`` from the beams when not given)."""
        r = np.asarray(ranges, dtype=np.float32)
        if angle_max is None:
            angle_max = angle_min + angle_increment * (r.size - 1)
        return self.store.types["sensor_msgs/msg/LaserScan"](
            header=self.header(t, frame), angle_min=angle_min, angle_max=angle_max,
            angle_increment=angle_increment, time_increment=time_increment,
            scan_time=0.0, range_min=range_min,
            range_max=range_max, ranges=r, intensities=np.zeros(0, dtype=np.float32),
        )  # fmt: skip

    def _pose(self, p: Pose) -> Any:
        types = self.store.types
        return types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=p.x, y=p.y, z=0.0),
            orientation=self.quaternion(p.theta),
        )

    def quaternion(self, theta: float, *, upside_down: bool = False) -> Any:
        """The rotation by ``theta`` about z (then by pi about x when ``upside_down``)."""
        h = 0.5 * theta
        if upside_down:  # Rz(theta) * Rx(pi)
            return self.store.types["geometry_msgs/msg/Quaternion"](
                x=math.cos(h), y=math.sin(h), z=0.0, w=0.0)
        return self.store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(h), w=math.cos(h))

    def odometry(self, t: float, pose: Pose, frame: str = "odom", child: str = "base_link") -> Any:
        """A ``nav_msgs/Odometry``: ``child`` at ``pose`` in ``frame``."""
        types = self.store.types
        return types["nav_msgs/msg/Odometry"](
            header=self.header(t, frame), child_frame_id=child,
            pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(pose),
                                                               covariance=np.zeros(36, dtype=np.float64)),
            twist=types["geometry_msgs/msg/TwistWithCovariance"](
                twist=types["geometry_msgs/msg/Twist"](
                    linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                    angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36, dtype=np.float64)),
        )  # fmt: skip

    def transforms(
        self, t: float, links: Sequence[tuple[str, str, Pose]], *, z: float = 0.0, upside_down: bool = False,
    ) -> Any:
        """A ``tf2_msgs/TFMessage`` of ``(parent, child, pose)`` links at ``t``, each ``z`` above its
        parent."""
        types = self.store.types
        out = [
            types["geometry_msgs/msg/TransformStamped"](
                header=self.header(t, parent), child_frame_id=child,
                transform=types["geometry_msgs/msg/Transform"](
                    translation=types["geometry_msgs/msg/Vector3"](x=p.x, y=p.y, z=z),
                    rotation=self.quaternion(p.theta, upside_down=upside_down)),
            )
            for parent, child, p in links
        ]  # fmt: skip
        return types["tf2_msgs/msg/TFMessage"](transforms=out)


class BagWriter(MessageMaker):
    """A bag of format ``fmt`` (one of :data:`FORMATS`) at ``path``, written message by message;
    a context manager (the bag is complete when it closes)."""

    def __init__(self, path: Path, fmt: str) -> None:
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        super().__init__(fmt == "ros1")
        if self.ros1:
            self.writer: Any = Writer1(path)
        else:
            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        self.connections: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        self.writer.open()
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.writer.close()

    # ------------------------------------------------------------------ writing
    def write(self, topic: str, t: float, msg: Any) -> None:
        """``msg`` on ``topic``, recorded at ``t``."""
        self.write_raw(topic, msg.__msgtype__, t, self.serialize(msg))

    def write_raw(self, topic: str, msgtype: str, t: float, data: bytes) -> None:
        """Bytes as they are (a damaged message) on ``topic`` of type ``msgtype``."""
        conn = self.connections.get(topic)
        if conn is None:
            conn = self.writer.add_connection(topic, msgtype, typestore=self.store)
            self.connections[topic] = conn
        sec, nsec = stamp_of(t)
        self.writer.write(conn, sec * 1_000_000_000 + nsec, data)


def write_scans_bag(
    path: Path,
    fmt: str,
    scans: Sequence[LaserScan],
    *,
    odometry: str = "topic",
    mount: Pose | None = None,
    truth: Sequence[Pose | None] | None = None,
) -> Path:
    """A bag of ``scans`` (the CARMEN reader's): ``/scan`` (their ranges, ``inf`` for no return,
    their bearings as ``angle_min`` and a constant increment, ``range_max`` their maximum range),
    the robot's odometry at each scan's time on ``/odom`` (``odometry="topic"``) or as
    ``odom -> base_link`` on ``/tf`` (``odometry="tf"``), the laser at ``mount`` on the robot on
    ``/tf_static`` (none when ``mount`` is None: the laser at the base's origin) and, with
    ``truth`` (the laser's true poses; None for a scan without one), the robot's true pose on
    ``/ground_truth``. The robot's
    poses are the scans' laser poses composed with ``mount`` inverted."""
    unmount = (mount or Pose()).inverse()
    with BagWriter(path, fmt) as bag:
        if mount is not None:
            link = [("base_link", LASER_FRAME, mount)]
            bag.write("/tf_static", scans[0].t, bag.transforms(scans[0].t, link, z=0.3))
        for k, s in enumerate(scans):
            a = np.asarray(s.angles)
            inc = float(a[-1] - a[0]) / (a.size - 1)
            bag.write("/scan", s.t, bag.scan(s.t, s.ranges, float(a[0]), inc, angle_max=float(a[-1]),
                                             range_max=s.max_range))
            robot = s.odom.compose(unmount)
            if odometry == "tf":
                bag.write("/tf", s.t, bag.transforms(s.t, [("odom", "base_link", robot)]))
            else:
                bag.write("/odom", s.t, bag.odometry(s.t, robot))
            if truth is not None and truth[k] is not None:
                bag.write("/ground_truth", s.t, bag.odometry(s.t, truth[k].compose(unmount), frame="map"))
    return path
