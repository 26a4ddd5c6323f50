"""ROS 2 messages made from a log's scans: ``sensor_msgs/msg/LaserScan`` and
``nav_msgs/msg/Odometry`` as CDR bytes (with their 4-byte encapsulation header, as a ROS 2
publisher, zenoh-bridge-ros2dds and rmw_zenoh carry them), built with the ``rosbags`` library's
typestore (ROS 2 Humble definitions; no ROS install). ``wiremap play`` publishes them so that a
live robot (``wiremap robot --scan-key --odom-key``) can be tried without a robot.

Conventions (those :mod:`agents.files.rosbag` reads back): the beams as ``angle_min`` and a
constant ``angle_increment`` (the scan's first bearing and the mean step), ``angle_max`` the last
bearing; a scan's no-returns (``inf``) stay ``+inf`` (REP 117); ``range_min`` 0, ``range_max``
the scanner's; the header's frame ``laser``. The odometry is the robot's base in ``odom``
(``child_frame_id`` ``base_link``): the laser's pose composed with its mount inverted, the
heading as a rotation about z. Stamps are the scan's time (seconds, at least 1 ns: a zero stamp
means "none" in ROS).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mapping.se2 import Pose

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"


class Ros2Messages:
    """Builds and serialises the two message types (one typestore, made once)."""

    def __init__(
        self, laser_frame: str = "laser", odom_frame: str = "odom", base_frame: str = "base_link"
    ) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.store = get_typestore(Stores.ROS2_HUMBLE)
        self.types = self.store.types
        self.laser_frame, self.odom_frame, self.base_frame = laser_frame, odom_frame, base_frame

    def _header(self, t: float, frame: str) -> Any:
        ns = max(1, round(t * 1e9))
        stamp = self.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return self.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def scan(
        self, t: float, ranges: Any, angles: Any, max_range: float, time_increment: float = 0.0
    ) -> bytes:
        """A ``LaserScan`` of beams at ``angles`` (increasing, evenly spaced) with ``ranges``,
        ``time_increment`` seconds apart (``scan_time``, the time between scans, 0: not known)."""
        a = np.asarray(angles, dtype=np.float64)
        r = np.asarray(ranges, dtype=np.float32)
        inc = float(a[-1] - a[0]) / (a.size - 1) if a.size > 1 else 0.0
        msg = self.types[SCAN_TYPE](
            header=self._header(t, self.laser_frame), angle_min=float(a[0]), angle_max=float(a[-1]),
            angle_increment=inc, time_increment=float(time_increment),
            scan_time=0.0, range_min=0.0,
            range_max=float(max_range), ranges=r, intensities=np.zeros(0, dtype=np.float32),
        )
        return bytes(self.store.serialize_cdr(msg, SCAN_TYPE))

    def odometry(self, t: float, pose: Pose) -> bytes:
        """An ``Odometry`` with the robot's base at ``pose`` in the odometry frame."""
        ty = self.types
        msg = ty[ODOM_TYPE](
            header=self._header(t, self.odom_frame), child_frame_id=self.base_frame,
            pose=ty["geometry_msgs/msg/PoseWithCovariance"](
                pose=ty["geometry_msgs/msg/Pose"](
                    position=ty["geometry_msgs/msg/Point"](x=pose.x, y=pose.y, z=0.0),
                    orientation=self._yaw(pose.theta)),
                covariance=np.zeros(36, dtype=np.float64)),
            twist=ty["geometry_msgs/msg/TwistWithCovariance"](
                twist=ty["geometry_msgs/msg/Twist"](
                    linear=ty["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                    angular=ty["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36, dtype=np.float64)),
        )  # fmt: skip
        return bytes(self.store.serialize_cdr(msg, ODOM_TYPE))

    def laser_mount(self, t: float, mount: Pose) -> bytes:
        """A ``tf2_msgs/TFMessage`` (``/tf_static``) with the laser's ``mount`` on the robot's base:
        ``base_link -> laser``."""
        ty = self.types
        msg = ty[TF_TYPE](transforms=[ty["geometry_msgs/msg/TransformStamped"](
            header=self._header(t, self.base_frame), child_frame_id=self.laser_frame,
            transform=ty["geometry_msgs/msg/Transform"](
                translation=ty["geometry_msgs/msg/Vector3"](x=mount.x, y=mount.y, z=0.0),
                rotation=self._yaw(mount.theta)),
        )])  # fmt: skip
        return bytes(self.store.serialize_cdr(msg, TF_TYPE))

    def _yaw(self, theta: float) -> Any:
        """A ``geometry_msgs/Quaternion`` turning ``theta`` radians about z."""
        h = 0.5 * theta
        return self.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(h), w=math.cos(h))

    def of_scan(self, ls: Any) -> tuple[bytes, bytes]:
        """``(odometry, scan)`` of one scan of a log (:class:`agents.files.carmen.LaserScan`): the
        robot's base where the scan's laser pose and mount put it."""
        base = ls.odom.compose(ls.mount.inverse())
        return self.odometry(ls.t, base), self.scan(ls.t, ls.ranges, ls.angles, ls.max_range,
                                                    ls.time_increment)
