"""Real logs as fleets: a CARMEN log split into N robots (``wiremap run --carmen LOG --robots N``).

Robot ``k`` replays scans ``[i0, i1)`` of the log (:func:`split`: N stretches of equal length
along the log, each running on into the next by ``overlap`` of a stretch, so that neighbours
see common walls) through its own particle filter, in its own odometry frame starting at the
origin (the first scan of its stretch is the identity), and publishes with an unknown origin:
only global registration can put the robots together.

Scoring (:func:`score_map`): a map in some robot's frame is placed in the log's truth frame by
that robot's true first pose (``NAME.truth.tsv``, one row per laser line) -- no fitting -- and
its *endpoint precision* is the fraction of points sampled every 5 cm along its walls that lie
within 0.2 m of a real scan endpoint placed at its truth pose (the data README's measure).

Workaround, to drop when the project reader accepts them (a colleague is rewriting
:mod:`agents.files.carmen`, and ``mapping/lidar_metrics.py`` will measure precision against
endpoints): :func:`read_log` strips the ``host timestamp`` tail of ``PARAM`` lines before
calling :func:`agents.files.carmen.read_carmen` (which takes everything after the name as the
value), and :func:`endpoint_precision` is a minimal local version of that measure.
"""

from __future__ import annotations

import gzip
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapping.se2 import Pose
from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]

MAX_RANGE = 20.0  # as `wiremap map --carmen`
ENDPOINT_TOL = 0.2
SAMPLE_STEP = 0.05


def read_log(path: str | os.PathLike[str]) -> list[Any]:
    """The log's laser scans (:func:`agents.files.carmen.read_carmen`) after dropping the
    ``host timestamp`` tail of ``PARAM name value host timestamp`` lines (workaround)."""
    from agents.files.carmen import read_carmen

    p = Path(path)
    opener = gzip.open if p.suffix == ".gz" else open
    with opener(p, "rt") as fh:  # type: ignore[operator]
        lines = [(" ".join(t.split()[:3]) + "\n") if t.startswith("PARAM ") else t for t in fh]
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d) / "log.txt"
        tmp.write_text("".join(lines))
        return list(read_carmen(tmp))


def truth_path(log: str | os.PathLike[str]) -> Path:
    p = Path(log)
    name = p.name[: -len(".log.gz")] if p.name.endswith(".log.gz") else p.name.rsplit(".", 1)[0]
    return p.with_name(f"{name}.truth.tsv")


def read_truth(log: str | os.PathLike[str]) -> list[Pose] | None:
    """``NAME.truth.tsv`` beside the log: one pose per laser line (None when absent)."""
    tp = truth_path(log)
    if not tp.is_file():
        return None
    out = []
    for ln in tp.read_text().splitlines():
        tok = ln.split()
        if len(tok) >= 4 and not tok[0].startswith("#"):
            try:
                out.append(Pose(float(tok[1]), float(tok[2]), float(tok[3])))
            except ValueError:
                continue
    return out


def split(n_scans: int, robots: int, overlap: float = 0.3) -> list[tuple[int, int]]:
    """``robots`` stretches ``[i0, i1)`` of equal length along ``n_scans`` scans, each running
    on into the next by ``overlap`` of a stretch."""
    if robots < 1 or n_scans < robots:
        raise ValueError(f"cannot split {n_scans} scans among {robots} robots")
    piece = n_scans / robots
    out = []
    for k in range(robots):
        i0 = round(k * piece)
        i1 = min(n_scans, round((k + 1) * piece + overlap * piece))
        out.append((i0, i1))
    return out


def robot_steps(opts: Any) -> Iterator[Any]:
    """The robot's loop (:func:`agents.mapping_run.run_filter`) over scans ``opts.scans`` of
    ``opts.carmen``, its filter starting at the identity (its own odometry frame)."""
    from agents import mapping_run as mr
    from mapping.filter import WireframeFilter

    scans = read_log(opts.carmen)
    i0, i1 = opts.scans if opts.scans is not None else (0, len(scans))
    part = scans[i0:i1]
    if not part:
        raise ValueError(f"no scans in {i0}:{i1} of {opts.carmen}")
    max_range = min(float(part[0].max_range), MAX_RANGE)
    cfg = mr.filter_config_for(int(opts.particles), float(opts.threshold), max_range, fov=mr.scan_fov(part[0].angles))
    filt = WireframeFilter(cfg, mr.seeds_for(int(opts.seed))["filter"], initial_pose=Pose.identity())
    return mr.run_filter(mr.carmen_inputs(part, max_range=max_range), filt, total=len(part))


def endpoints(scans: list[Any], truth: list[Pose], max_range: float = MAX_RANGE) -> FloatArray:
    """Every scan's endpoints (returns under ``max_range``) placed at its truth pose."""
    out = []
    for ls, p in zip(scans, truth):
        r = np.asarray(ls.ranges, dtype=np.float64)
        ok = np.isfinite(r) & (r < min(max_range, float(ls.max_range)))
        a = np.asarray(ls.angles, dtype=np.float64)[ok]
        pts = np.column_stack([r[ok] * np.cos(a), r[ok] * np.sin(a)])
        out.append(p.apply(pts))
    return np.concatenate(out) if out else np.zeros((0, 2))


def endpoint_precision(wf: Wireframe, ends: FloatArray, tol: float = ENDPOINT_TOL, step: float = SAMPLE_STEP) -> float:
    """Fraction of points every ``step`` along the walls within ``tol`` of an endpoint (local
    stand-in for ``mapping/lidar_metrics.py``)."""
    from scipy.spatial import cKDTree

    from mapping.metrics import sample_walls

    if wf.n_edges == 0 or len(ends) == 0:
        return 0.0
    pts, w, _ = sample_walls(wf, step)
    if len(pts) == 0:
        return 0.0
    d, _ = cKDTree(ends).query(pts, k=1, distance_upper_bound=tol)
    return float(np.sum(np.asarray(w)[np.isfinite(d)]) / np.sum(w))


def pose_error(found: Pose, true: Pose) -> tuple[float, float]:
    """Translation (m) and rotation (deg) error of a registered pose."""
    return (
        math.hypot(found.x - true.x, found.y - true.y),
        math.degrees(abs(math.remainder(found.theta - true.theta, 2 * math.pi))),
    )
