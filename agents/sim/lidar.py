"""A simulated 2-D scanning lidar: ray casting against wall segments.

The lidar turns a world's walls (e.g. ``World.truth.segments()``) into the raw ranges a planar
laser scanner would return from a robot pose: one range per beam, beams evenly spread over the
field of view and centred on the robot's heading. :func:`mapping.extract.extract_corners` turns
these ranges into a corner scan, and :mod:`agents.files.carmen` writes them as a CARMEN log.

Conventions
-----------
* **Beam bearings** (:meth:`LidarConfig.angles`) are in the robot frame, increasing
  (counterclockwise). A field of view below a full turn has a beam on each edge,
  ``-fov/2`` and ``+fov/2`` (the CARMEN ``FLASER`` convention: resolution ``fov / (beams - 1)``).
  A full turn (``fov == 2*pi``) has ``beams`` evenly spaced bearings starting at ``-pi`` without
  repeating it at ``+pi``.
* **No return** is ``np.inf``: a beam that meets no wall within ``max_range``. A noisy reading
  that lands at or beyond ``max_range`` is also reported as no return (a real scanner saturates
  the same way), and noise never makes a range negative.
* **Walls are opaque from both sides**: a segment blocks a beam whichever way it is directed. A
  beam through the exact shared end point of two segments hits them (end points are inclusive),
  so closed rooms never leak.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapping.se2 import Pose

FloatArray = NDArray[np.float64]

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class LidarConfig:
    """A planar laser scanner.

    Parameters
    ----------
    beams : int
        Number of beams per scan (>= 2).
    fov : float
        Field of view in radians, ``0 < fov <= 2*pi``, centred on the heading.
    max_range : float
        Range in metres beyond which a beam returns nothing.
    sigma : float
        Standard deviation of the additive Gaussian range noise in metres (>= 0).

    Raises
    ------
    ValueError
        With the reason, when a value is out of its range.
    """

    beams: int = 361
    fov: float = math.pi
    max_range: float = 10.0
    sigma: float = 0.01

    def __post_init__(self) -> None:
        if isinstance(self.beams, bool) or not isinstance(self.beams, (int, np.integer)):
            raise ValueError(f"beams must be an integer, got {self.beams!r}")
        if self.beams < 2:
            raise ValueError(f"beams must be at least 2, got {self.beams}")
        if not (math.isfinite(self.fov) and 0.0 < self.fov <= TWO_PI + 1e-9):
            raise ValueError(f"fov must be in (0, 2*pi] radians, got {self.fov}")
        if not (math.isfinite(self.max_range) and self.max_range > 0.0):
            raise ValueError(f"max_range must be a positive number of metres, got {self.max_range}")
        if not (math.isfinite(self.sigma) and self.sigma >= 0.0):
            raise ValueError(f"sigma must be a non-negative number of metres, got {self.sigma}")

    @property
    def full_circle(self) -> bool:
        """True when the beams cover a whole turn (the scan is cyclic)."""
        return self.fov >= TWO_PI - 1e-9

    def angles(self) -> FloatArray:
        """Beam bearings in the robot frame, increasing (counterclockwise), shape ``(beams,)``."""
        if self.full_circle:
            return np.asarray(-math.pi + TWO_PI * np.arange(self.beams) / self.beams, dtype=np.float64)
        return np.linspace(-0.5 * self.fov, 0.5 * self.fov, self.beams, dtype=np.float64)


def raycast(
    segments: FloatArray,
    pose: Pose,
    config: LidarConfig,
    rng: np.random.Generator | None = None,
) -> FloatArray:
    """Ranges a lidar at ``pose`` measures against the walls ``segments``.

    Parameters
    ----------
    segments : (m, 2, 2) float
        World-frame walls, ``[k, 0]`` the start and ``[k, 1]`` the end (direction is ignored:
        walls are opaque from both sides).
    pose : Pose
        The sensor's pose in the world frame; beam bearings are relative to its heading.
    config : LidarConfig
        Beams, field of view, maximum range and noise.
    rng : numpy.random.Generator or None
        Source of the range noise; ``None`` (or ``config.sigma == 0``) gives exact ranges.

    Returns
    -------
    (beams,) float64
        Range per beam in metres, ``np.inf`` where there is no return (see the module notes).

    Notes
    -----
    Walls whose bounding box does not meet the range disc are culled first, so the cost is
    ``beams x nearby walls`` whatever the size of the world; the intersection test is one
    vectorised ``(beams, walls)`` computation (ray ``o + s d`` against ``p + u (q - p)``:
    ``s = ((p - o) x e) / (d x e)``, ``u = ((p - o) x d) / (d x e)``, a hit when
    ``s > 0`` and ``0 <= u <= 1``).
    """
    out = cast_ranges(segments, pose, config)
    r_max = float(config.max_range)
    if rng is not None and config.sigma > 0.0:
        seen = np.isfinite(out)
        noisy = out[seen] + rng.normal(0.0, config.sigma, size=int(seen.sum()))
        noisy = np.maximum(noisy, 0.0)
        noisy[noisy >= r_max] = np.inf
        out[seen] = noisy
    return np.asarray(out, dtype=np.float64)


def cast_ranges(
    segments: FloatArray,
    pose: Pose,
    config: LidarConfig,
    *,
    glass: NDArray[np.bool_] | None = None,
    glass_min_sin: float = 1.0,
) -> FloatArray:
    """Exact ranges (no noise) from ``pose`` to the nearest of ``segments``, as :func:`raycast`.

    Parameters
    ----------
    segments, pose, config
        As :func:`raycast` (``config.sigma`` is not used).
    glass : (m,) bool, optional
        Segments that are glass: a beam meets one only when it strikes it near normal
        incidence, ``|sin(angle between beam and segment)| >= glass_min_sin``; at any other
        angle it passes through to whatever lies behind (:mod:`agents.sim.real_lidar`).
    glass_min_sin : float
        See ``glass`` (``cos`` of the largest angle from the normal that still returns).

    Returns
    -------
    (beams,) float64
        Range per beam, ``np.inf`` where no segment is met within ``config.max_range``.

    Raises
    ------
    ValueError
        ``segments`` not of shape ``(m, 2, 2)`` or not finite, or ``glass`` not of shape ``(m,)``.
    """
    seg = np.asarray(segments, dtype=np.float64)
    if seg.size == 0:
        seg = seg.reshape(0, 2, 2)
    if seg.ndim != 3 or seg.shape[1:] != (2, 2):
        raise ValueError(f"segments must have shape (m, 2, 2), got {seg.shape}")
    if not np.all(np.isfinite(seg)):
        raise ValueError("segments must have finite coordinates")
    if glass is not None:
        glass = np.asarray(glass, dtype=bool)
        if glass.shape != (len(seg),):
            raise ValueError(f"glass must have shape ({len(seg)},), got {glass.shape}")
    beams = int(config.beams)
    out = np.full(beams, np.inf)
    r_max = float(config.max_range)
    ox, oy = pose.x, pose.y

    if len(seg):
        # Cull: distance from the sensor to each wall's bounding box must be <= max_range.
        lo = np.minimum(seg[:, 0], seg[:, 1])
        hi = np.maximum(seg[:, 0], seg[:, 1])
        dx = np.maximum(np.maximum(lo[:, 0] - ox, ox - hi[:, 0]), 0.0)
        dy = np.maximum(np.maximum(lo[:, 1] - oy, oy - hi[:, 1]), 0.0)
        near = dx * dx + dy * dy <= r_max * r_max
        seg = seg[near]
        if glass is not None:
            glass = glass[near]

    if len(seg):
        bearings = config.angles() + pose.theta
        d = np.stack([np.cos(bearings), np.sin(bearings)], axis=1)  # (B, 2)
        p = seg[:, 0] - np.array([ox, oy])  # (S, 2) wall start relative to the sensor
        e = seg[:, 1] - seg[:, 0]  # (S, 2)
        denom = d[:, 0:1] * e[None, :, 1] - d[:, 1:2] * e[None, :, 0]  # d x e, (B, S)
        p_cross_e = p[:, 0] * e[:, 1] - p[:, 1] * e[:, 0]  # (S,)
        p_cross_d = p[None, :, 0] * d[:, 1:2] - p[None, :, 1] * d[:, 0:1]  # (B, S)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = p_cross_e[None, :] / denom
            u = p_cross_d / denom
        # Parallel rays (denom == 0) never hit: a wall seen edge-on has no width.
        eps = 1e-12
        hit = (denom != 0.0) & (s > 0.0) & (u >= -eps) & (u <= 1.0 + eps)
        if glass is not None and glass.any():
            # |d x e| / |e| is the sine of the angle between the beam and the pane.
            length = np.hypot(e[:, 0], e[:, 1])
            with np.errstate(divide="ignore", invalid="ignore"):
                steep = np.abs(denom) >= glass_min_sin * length[None, :]
            hit &= ~glass[None, :] | steep
        s = np.where(hit, s, np.inf)
        out = s.min(axis=1)
        out[out > r_max] = np.inf
    return np.asarray(out, dtype=np.float64)
