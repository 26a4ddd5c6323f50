"""Real-lidar front end: one laser scan's ranges -> the corner scan and the points to match.

The filter takes a labelled corner scan (:mod:`mapping.extract`, split-and-merge) for its
likelihoods and merge, and -- with :attr:`mapping.filter.FilterConfig.point_match` -- the raw
points for a point-to-line match against the map (:mod:`mapping.scan_match`). This module makes
both from one scan of a real scanner, whose ranges differ from the simulator's in ways the
front end has to absorb:

* a **limited field of view** (180 degrees on the CARMEN logs), so a scan's ends are frontiers
  on the first and last beam (the extractor handles that) and the filter's predicted scan must
  use the same ``fov``;
* a **saturation value** for "no return" (81.91, 51.2 or 32.767 m depending on the scanner) and
  long, grazing returns far beyond the range the map is built to (``max_range``): the caller
  maps both to ``inf``; the points keep returns up to ``point_range`` (far points still pin the
  heading down);
* **clutter** (chairs, people, glass): the extractor drops short pieces; the point matcher's
  robust kernel and normal test drop the points.

Choices
-------
* Points are every ``point_stride``-th return (a 0.5-degree scanner gives twice the points of
  a 1-degree one at twice the cost and the same information, their errors being correlated).
* Points nearer than ``min_range`` are dropped (the robot's own body, a person next to it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapping.extract import ExtractConfig, extract_corners
from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]

__all__ = ["FrontendConfig", "LidarFrontend", "odometry_overrides", "scan_points"]


@dataclass(frozen=True)
class FrontendConfig:
    """Parameters of :class:`LidarFrontend`.

    Parameters
    ----------
    point_range : float
        Returns farther than this (metres) are not matched (default 20).
    min_range : float
        Returns nearer than this are not matched (default 0.3).
    point_stride : int
        Keep every ``point_stride``-th beam's return (default 1).
    max_beam_spacing : float
        Beam spacing (radians) above which ``point_stride`` is 1 whatever it says (default 1.5
        degrees): coarse scanners keep all their points.
    """

    point_range: float = 20.0
    min_range: float = 0.3
    point_stride: int = 1
    max_beam_spacing: float = math.radians(1.5)

    def __post_init__(self) -> None:
        if not (self.point_range > self.min_range >= 0):
            raise ValueError("need point_range > min_range >= 0")
        if self.point_stride < 1:
            raise ValueError("point_stride must be >= 1")


def odometry_overrides(trans_per_m: float = 0.05, rot_per_m: float = math.radians(2.0)) -> dict[str, float]:
    """:class:`mapping.filter.FilterConfig` overrides (dotted keys, :func:`mapping.config.with_overrides`) whose odometry noise model covers a robot
    whose odometry errs by ``trans_per_m`` of the distance and ``rot_per_m`` radians per metre
    (defaults: the CARMEN development logs' 5 % and 2 degrees per metre), with the filter's
    usual margin of about 1.4 (it should not trust its odometry more than it deserves).

    The filter's defaults (3 % and 0.17 degrees per metre) are 1.5 times the *simulator's*
    odometry noise. On the real logs -- a scan every metre, turning 15 degrees between scans
    (median) -- they made the pose prior ten times too tight in heading: the ICP's gate and
    Mahalanobis test then rejected the right correction, and the pose ran on odometry. This
    alone took the seven logs' median ATE from 1.59 m to 0.42 m (docs/experiments.md, "Real
    lidar")."""
    return {"odometry.trans_per_m": round(1.4 * trans_per_m, 3), "odometry.rot_per_m": round(1.43 * rot_per_m, 3)}


def scan_points(ranges: FloatArray, angles: FloatArray, config: FrontendConfig) -> FloatArray:
    """The points to match (robot frame, bearing order): finite returns within
    ``[min_range, point_range]``, every ``point_stride``-th beam."""
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    a = np.asarray(angles, dtype=np.float64).reshape(-1)
    stride = config.point_stride
    if len(a) > 1 and abs(a[1] - a[0]) > config.max_beam_spacing:
        stride = 1
    r, a = r[::stride], a[::stride]
    ok = np.isfinite(r) & (r >= config.min_range) & (r <= config.point_range)
    return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=1)


class LidarFrontend:
    """Turns one real scan into ``(corner scan, points)`` for :meth:`mapping.filter.WireframeFilter.step`.

    Parameters
    ----------
    config : FrontendConfig, optional
    extract : ExtractConfig, optional
        The split-and-merge settings (:func:`mapping.extract.extract_corners`).
    """

    def __init__(self, config: FrontendConfig | None = None, extract: ExtractConfig | None = None) -> None:
        self.config = config or FrontendConfig()
        self.extract = extract

    def scan(self, ranges: FloatArray, angles: FloatArray, max_range: float) -> tuple[Wireframe, FloatArray]:
        """The corner scan (returns at or beyond ``max_range`` are no return) and the points."""
        r = np.asarray(ranges, dtype=np.float64)
        corners = r.copy()
        with np.errstate(invalid="ignore"):
            corners[~(corners < max_range)] = np.inf
        if self.extract is None:
            wf = extract_corners(corners, angles, max_range)
        else:
            wf = extract_corners(corners, angles, max_range, self.extract)
        return wf, scan_points(r, angles, self.config)
