"""Rigid transforms of the plane, SE(2).

A :class:`Pose` ``(x, y, theta)`` maps points from its own (child) frame into its parent frame:
``p_parent = R(theta) @ p_child + (x, y)``. A robot pose in the map frame therefore turns a scan
taken in the robot frame into map coordinates with :meth:`Pose.apply`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def wrap_angle(a: float) -> float:
    """Wrap an angle to ``[-pi, pi)``."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def wrap_angles(a: FloatArray) -> FloatArray:
    """Vectorised :func:`wrap_angle`."""
    return np.asarray((a + np.pi) % (2.0 * np.pi) - np.pi, dtype=np.float64)


@dataclass(frozen=True, slots=True)
class Pose:
    """An element of SE(2): translation ``(x, y)`` in metres and heading ``theta`` in radians."""

    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.x) and math.isfinite(self.y) and math.isfinite(self.theta)):
            raise ValueError(f"pose must be finite, got ({self.x}, {self.y}, {self.theta})")
        object.__setattr__(self, "x", float(self.x))
        object.__setattr__(self, "y", float(self.y))
        object.__setattr__(self, "theta", wrap_angle(float(self.theta)))

    @classmethod
    def identity(cls) -> Pose:
        return cls(0.0, 0.0, 0.0)

    @classmethod
    def from_matrix(cls, m: FloatArray) -> Pose:
        """From a 3x3 homogeneous matrix (its rotation part is taken at face value)."""
        return cls(float(m[0, 2]), float(m[1, 2]), math.atan2(float(m[1, 0]), float(m[0, 0])))

    @classmethod
    def parse(cls, text: str) -> Pose:
        """Parse ``"X,Y,THETA"`` (metres, metres, radians); raises ``ValueError`` with the reason."""
        parts = text.split(",")
        if len(parts) != 3:
            raise ValueError(f"pose must be X,Y,THETA, got {text!r}")
        try:
            x, y, t = (float(p) for p in parts)
        except ValueError:
            raise ValueError(f"pose must be three numbers X,Y,THETA, got {text!r}") from None
        return cls(x, y, t)

    def as_matrix(self) -> FloatArray:
        c, s = math.cos(self.theta), math.sin(self.theta)
        return np.array([[c, -s, self.x], [s, c, self.y], [0.0, 0.0, 1.0]])

    def as_tuple(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.theta)

    def compose(self, other: Pose) -> Pose:
        """``self * other``: apply ``other`` first, then ``self``."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Pose(
            self.x + c * other.x - s * other.y,
            self.y + s * other.x + c * other.y,
            self.theta + other.theta,
        )

    __matmul__ = compose

    def inverse(self) -> Pose:
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Pose(-(c * self.x + s * self.y), -(-s * self.x + c * self.y), -self.theta)

    def between(self, other: Pose) -> Pose:
        """The relative motion ``self^-1 * other`` (e.g. an odometry increment)."""
        return self.inverse().compose(other)

    def apply(self, points: FloatArray) -> FloatArray:
        """Map ``(n, 2)`` points from this pose's frame into the parent frame."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        c, s = math.cos(self.theta), math.sin(self.theta)
        out = np.empty_like(p)
        out[:, 0] = c * p[:, 0] - s * p[:, 1] + self.x
        out[:, 1] = s * p[:, 0] + c * p[:, 1] + self.y
        return out

    def apply_inverse(self, points: FloatArray) -> FloatArray:
        """Map ``(n, 2)`` points from the parent frame into this pose's frame."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        c, s = math.cos(self.theta), math.sin(self.theta)
        dx, dy = p[:, 0] - self.x, p[:, 1] - self.y
        out = np.empty_like(p)
        out[:, 0] = c * dx + s * dy
        out[:, 1] = -s * dx + c * dy
        return out

    def distance(self, other: Pose) -> float:
        return math.hypot(self.x - other.x, self.y - other.y)

    def almost_equal(self, other: Pose, tol: float = 1e-9, angle_tol: float = 1e-9) -> bool:
        return (
            abs(self.x - other.x) <= tol
            and abs(self.y - other.y) <= tol
            and abs(wrap_angle(self.theta - other.theta)) <= angle_tol
        )


def increments(poses: Sequence[Pose]) -> list[Pose]:
    """The motion into each pose from the one before it, in that one's frame
    (``poses[k - 1].between(poses[k])``; the identity for the first): odometry from a track."""
    return [Pose.identity(), *(a.between(b) for a, b in itertools.pairwise(poses))] if poses else []
