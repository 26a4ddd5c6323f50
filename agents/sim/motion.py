"""Driving a route: true poses at a fixed time step and noisy odometry (paper Sec. IV-A, V).

The robot follows the route polyline exactly (its position is always on the route, so it never
leaves the route's corridor). It starts at the first point facing along the first segment. At
each interior vertex it turns in place to the next segment's direction: instantly when
``max_turn_rate`` is None, otherwise at that rate (rad/s), which costs time. Along a segment it
drives at ``speed``. Time advances in steps of ``dt``; a step may span several vertices. The
last step ends when the route's end is reached (the robot then stands still for the rest of
that step, so every step but the first is ``dt`` long).

Odometry: the increment ``u = true_{k-1}^-1 * true_k`` (in the previous robot frame) is
corrupted by zero-mean Gaussian noise whose standard deviation grows with the motion
(:class:`OdometryNoise`): translation noise on each axis with std ``trans_per_m * d +
trans_abs``, rotation noise with std ``rot_per_rad * |dtheta| + rot_per_m * d + rot_abs``,
where ``d`` is the distance and ``dtheta`` the heading change of the true increment.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import NDArray

from mapping.se2 import Pose, wrap_angle

__all__ = ["OdometryNoise", "Step", "dead_reckon", "drive", "noisy_increment"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class OdometryNoise:
    """Standard deviations of the odometry noise, proportional to motion.

    Attributes
    ----------
    trans_per_m : float
        Translation std per metre driven, on each axis (default 0.02: 2 cm per metre).
    rot_per_rad : float
        Rotation std per radian turned (default 0.02).
    rot_per_m : float
        Rotation std per metre driven, rad/m (default 0.002).
    trans_abs : float
        Translation std added per step, metres (default 0).
    rot_abs : float
        Rotation std added per step, radians (default 0).

    Raises
    ------
    ValueError
        On a negative or non-finite value.
    """

    trans_per_m: float = 0.02
    rot_per_rad: float = 0.02
    rot_per_m: float = 0.002
    trans_abs: float = 0.0
    rot_abs: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"odometry noise {f.name} must be a finite number >= 0, got {v!r}")
            object.__setattr__(self, f.name, float(v))

    @classmethod
    def none(cls) -> OdometryNoise:
        """Perfect odometry."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0)

    def stds(self, increment: Pose) -> tuple[float, float]:
        """``(translation std per axis, rotation std)`` for a true increment."""
        d = math.hypot(increment.x, increment.y)
        return (
            self.trans_per_m * d + self.trans_abs,
            self.rot_per_rad * abs(increment.theta) + self.rot_per_m * d + self.rot_abs,
        )


@dataclass(frozen=True)
class Step:
    """One time step of a drive.

    Attributes
    ----------
    t : float
        Simulation time, seconds.
    true_pose : Pose
        The robot's pose in the world frame.
    odometry : Pose
        Noisy motion increment since the previous step, in the previous robot frame
        (identity at step 0).
    """

    t: float
    true_pose: Pose
    odometry: Pose


def noisy_increment(increment: Pose, noise: OdometryNoise, rng: np.random.Generator) -> Pose:
    """``increment`` with Gaussian noise added to ``x``, ``y`` and ``theta`` (see module)."""
    st, sr = noise.stds(increment)
    e = rng.standard_normal(3)
    return Pose(increment.x + st * e[0], increment.y + st * e[1], increment.theta + sr * e[2])


def _true_poses(
    route: FloatArray, speed: float, dt: float, max_turn_rate: float | None
) -> list[tuple[float, Pose]]:
    """Poses at t = 0, dt, 2 dt, ... until the route's end is reached."""
    pts = route
    seg = np.diff(pts, axis=0)
    lengths = np.hypot(seg[:, 0], seg[:, 1])
    headings = np.arctan2(seg[:, 1], seg[:, 0])
    n = len(lengths)
    out: list[tuple[float, Pose]] = []
    k = 0  # current segment
    s = 0.0  # distance along it
    theta = float(headings[0]) if n else 0.0
    t = 0.0
    out.append((t, Pose(float(pts[0, 0]), float(pts[0, 1]), theta)))
    if n == 0:
        return out
    done = False
    while not done:
        budget = dt
        while budget > 1e-12:
            if k >= n:
                done = True
                break
            want = float(headings[k])
            diff = wrap_angle(want - theta)
            if abs(diff) > 1e-12:
                if max_turn_rate is None:
                    theta = want
                else:
                    turn = min(abs(diff), max_turn_rate * budget)
                    theta = wrap_angle(theta + math.copysign(turn, diff))
                    budget -= turn / max_turn_rate
                    if abs(wrap_angle(want - theta)) > 1e-12:
                        continue
                    theta = want
            move = min(float(lengths[k]) - s, speed * budget)
            s += move
            budget -= move / speed
            if float(lengths[k]) - s <= 1e-12:
                k += 1
                s = 0.0
        if k >= n:
            done = True
        t += dt
        if k < n:
            p = pts[k] + (s / lengths[k]) * seg[k]
        else:
            p = pts[-1]
        out.append((t, Pose(float(p[0]), float(p[1]), theta)))
    return out


def drive(
    route: FloatArray,
    *,
    speed: float = 0.5,
    dt: float = 0.5,
    noise: OdometryNoise | None = None,
    rng: np.random.Generator,
    max_turn_rate: float | None = None,
) -> list[Step]:
    """Follow ``route`` and return the true poses with noisy odometry, one :class:`Step` per
    ``dt`` (module docstring).

    Parameters
    ----------
    route : (k, 2) array
        Polyline in the world frame; repeated consecutive points are ignored. A single point
        gives one step.
    speed : float
        Driving speed, m/s (> 0).
    dt : float
        Time step, s (> 0).
    noise : OdometryNoise, optional
        Default :class:`OdometryNoise()` (2 %/m translation, 2 %/rad + 0.002 rad/m rotation).
    rng : numpy.random.Generator
        The only source of randomness (the odometry noise).
    max_turn_rate : float, optional
        Turn-in-place rate at vertices, rad/s (> 0); None turns instantly.

    Raises
    ------
    ValueError
        Bad shapes or non-positive/non-finite parameters.
    """
    r = np.asarray(route, dtype=np.float64)
    if r.ndim != 2 or r.shape[1] != 2 or len(r) == 0:
        raise ValueError(f"route must have shape (k, 2) with k >= 1, got {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError("route has non-finite coordinates")
    for name, v in (("speed", speed), ("dt", dt)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive number, got {v}")
    if max_turn_rate is not None and not (math.isfinite(max_turn_rate) and max_turn_rate > 0):
        raise ValueError(f"max_turn_rate must be positive or None, got {max_turn_rate}")
    noise = OdometryNoise() if noise is None else noise
    keep = np.ones(len(r), dtype=bool)
    keep[1:] = np.hypot(*np.diff(r, axis=0).T) > 1e-12
    r = r[keep]
    truth = _true_poses(r, float(speed), float(dt), max_turn_rate)
    steps = [Step(truth[0][0], truth[0][1], Pose.identity())]
    for (_, prev), (t, cur) in itertools.pairwise(truth):
        steps.append(Step(t, cur, noisy_increment(prev.between(cur), noise, rng)))
    return steps


def dead_reckon(steps: list[Step], start: Pose | None = None) -> list[Pose]:
    """Integrate the odometry of ``steps`` from ``start`` (default: step 0's true pose)."""
    if not steps:
        return []
    pose = steps[0].true_pose if start is None else start
    out = [pose]
    for s in steps[1:]:
        pose = pose.compose(s.odometry)
        out.append(pose)
    return out
