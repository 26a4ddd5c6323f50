"""Scan clean-up: what a scan loses before the filter uses it (mostly not in the paper).

A corner sensor's scan (paper Sec. IV-A) carries a few edges that are artefacts of the sensor
rather than walls. :func:`clean_scan` removes them in this order:

1. **gap bridges** (:func:`drop_gap_bridges`): an edge joining two loose ends (frontier or
   occlusion vertices that each end another edge) closes a gap between two walls: a false
   positive (the sensor's ``p_fp``);
2. **walls along a line of sight** (:func:`drop_line_of_sight`, paper Sec. IV-A: a pair
   "colinear along the same line of sight" cannot be a wall seen by the sensor);
3. **the budget** (:func:`budget_scan`): longest walls first;
4. **short frontier fragments** (:func:`fragment_mask`): kept as evidence (a fragment says the
   wall is there), left out of the scan that is matched and merged (its direction is mostly
   corner noise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapping.config import check_number
from mapping.wireframe import Label, Wireframe

BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

__all__ = [
    "CleanScan",
    "CleanupConfig",
    "budget_scan",
    "clean_scan",
    "drop_fragments",
    "drop_gap_bridges",
    "drop_line_of_sight",
    "fragment_mask",
]


@dataclass(frozen=True)
class CleanupConfig:
    """What :func:`clean_scan` removes (``cleanup.*`` settings; evidence in docs/experiments.md).

    Parameters
    ----------
    drop_gap_bridges : bool
        Drop edges that join two loose ends: on a long corridor the false edge across it at the
        range limit matched the next scan's and dragged the pose 0.2-0.5 m back.
    min_line_distance : float
        Drop edges whose line passes within this (metres) of the robot: a wall along a line of
        sight cannot be seen, so such an edge joins an occlusion to its frontier.
    min_fragment_length : float
        Frontier-ended edges shorter than this (metres) are evidence only: a 2 cm corner error
        tilts a 0.2 m piece by 11 degrees, so it would not merge into its wall.

    Raises
    ------
    ValueError
        On a negative or non-finite length.
    """

    drop_gap_bridges: bool = True
    min_line_distance: float = 0.15
    min_fragment_length: float = 0.4

    def __post_init__(self) -> None:
        check_number("min_line_distance", self.min_line_distance, 0.0)
        check_number("min_fragment_length", self.min_fragment_length, 0.0)


@dataclass(frozen=True)
class CleanScan:
    """A scan after :func:`clean_scan`.

    Attributes
    ----------
    evidence : Wireframe
        Without gap bridges and walls along a line of sight, within the budget: what the
        likelihood and the contradictions use.
    scan : Wireframe
        ``evidence`` without its short frontier fragments: what is matched and merged.
    kept : (m,) int64
        The edge of ``evidence`` of each edge of ``scan``.
    """

    evidence: Wireframe
    scan: Wireframe
    kept: IntArray


def clean_scan(scan: Wireframe, config: CleanupConfig, max_vertices: int) -> CleanScan:
    """The evidence scan and the scan to match and merge (module docstring, steps 1-4).

    Parameters
    ----------
    scan : Wireframe
        The sensor's scan (robot frame).
    config : CleanupConfig
    max_vertices : int
        Vertex budget of the scan (:attr:`mapping.filter.FilterConfig.max_scan_vertices`).

    Returns
    -------
    CleanScan
    """
    if config.drop_gap_bridges:
        scan = drop_gap_bridges(scan)
    evidence = budget_scan(drop_line_of_sight(scan, config.min_line_distance), max_vertices)
    kept = fragment_mask(evidence, config.min_fragment_length)
    kept_idx = np.flatnonzero(kept)
    merged = evidence if kept.all() else evidence.subgraph_edges(kept)
    return CleanScan(evidence, merged, kept_idx)


def fragment_mask(scan: Wireframe, min_length: float) -> BoolArray:
    """The scan edges to keep: all but those shorter than ``min_length`` with a frontier end
    (see :attr:`CleanupConfig.min_fragment_length`)."""
    if scan.n_edges == 0 or min_length <= 0:
        return np.ones(scan.n_edges, dtype=bool)
    fr = scan.labels[scan.edges] == Label.FRONTIER
    return np.asarray(~((scan.edge_lengths() < min_length) & fr.any(axis=1)))


def drop_fragments(scan: Wireframe, min_length: float) -> Wireframe:
    """Drop scan edges shorter than ``min_length`` that have a frontier end (see
    :attr:`CleanupConfig.min_fragment_length`)."""
    keep = fragment_mask(scan, min_length)
    return scan if keep.all() else scan.subgraph_edges(keep)


def drop_line_of_sight(scan: Wireframe, min_distance: float) -> Wireframe:
    """Drop scan edges (robot frame) whose supporting line passes within ``min_distance`` of the
    robot at the origin (see :attr:`CleanupConfig.min_line_distance`)."""
    if scan.n_edges == 0 or min_distance <= 0:
        return scan
    s = scan.segments()
    d = s[:, 1] - s[:, 0]
    length = np.hypot(d[:, 0], d[:, 1])
    cross = np.abs(s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0])
    bad = cross < min_distance * np.maximum(length, 1e-12)
    return scan.subgraph_edges(~bad) if bad.any() else scan


def drop_gap_bridges(scan: Wireframe) -> Wireframe:
    """Drop scan edges that join two non-nominal vertices each of which also ends another edge
    (see :attr:`CleanupConfig.drop_gap_bridges`)."""
    if scan.n_edges == 0:
        return scan
    din, dout = scan.degree()
    loose = (scan.labels != Label.NOMINAL) & (din + dout >= 2)
    bad = loose[scan.edges[:, 0]] & loose[scan.edges[:, 1]]
    return scan.subgraph_edges(~bad) if bad.any() else scan


def budget_scan(scan: Wireframe, max_vertices: int) -> Wireframe:
    """Keep whole walls, longest first, while the scan has at most ``max_vertices`` vertices."""
    if scan.n_vertices <= max_vertices:
        return scan
    order = np.argsort(-scan.edge_lengths(), kind="stable")
    used = np.zeros(scan.n_vertices, dtype=bool)
    keep = np.zeros(scan.n_edges, dtype=bool)
    count = 0
    for e in order.tolist():
        a, b = (int(v) for v in scan.edges[e])
        extra = int(not used[a]) + int(not used[b])
        if count + extra > max_vertices:
            continue
        used[a] = used[b] = True
        count += extra
        keep[e] = True
    return scan.subgraph_edges(keep)
