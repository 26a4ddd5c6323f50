"""CARMEN log files: read real laser scans with odometry, write simulated ones.

CARMEN logs are text, one message per line, the message type first. This module reads the
laser messages and the parameters that describe the scanner, and writes logs that CARMEN tools
(and this reader) understand.

Messages read
-------------
``FLASER num_readings [range_readings] x y theta odom_x odom_y odom_theta ipc_timestamp ipc_hostname logger_timestamp``
    The front laser. ``x y theta`` is the laser's pose *as the logger knew it* -- in corrected
    logs a pose estimate, never a measurement -- so it is ignored; the **odometry**
    ``odom_x odom_y odom_theta`` is used. Old logs without ``ipc_hostname logger_timestamp``
    are accepted too.
``ROBOTLASER1 laser_type start_angle field_of_view angular_resolution maximum_range accuracy remission_mode num_readings [range_readings] num_remissions [remissions] laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv forward_safety side_safety turn_axis timestamp hostname logger_timestamp``
    A laser with its own geometry: bearings ``start_angle + k * angular_resolution``, its own
    ``maximum_range`` (when positive). The odometry is ``robot_x robot_y robot_theta``; the
    laser's mounting offset is ``robot^-1 * laser`` from the same line.
``RAWLASER1 laser_type start_angle field_of_view angular_resolution maximum_range accuracy remission_mode num_readings [range_readings] num_remissions [remissions] ipc_timestamp hostname logger_timestamp``
    A laser without a pose: its odometry is that of the latest ``ODOM`` line before it (scans
    before the first ``ODOM`` are skipped).
``ODOM x y theta tv rv accel ipc_timestamp hostname logger_timestamp``
    Robot odometry. **Which wins:** a laser line that carries an odometry pose (``FLASER``,
    ``ROBOTLASER1``) uses its own, which the logger recorded for the scan's time; ``ODOM`` lines
    are used only for ``RAWLASER1`` scans, which carry none.
``PARAM name value``
    Parameters, wherever they appear in the file (see below).

Every other message type (``RLASER``, ``TRUEPOS``, ``NMEAGGA``, ...) is skipped, as are empty
lines and lines starting with ``#``. A malformed line of a type read here (a field that is not a
number, a wrong field count) raises :class:`CarmenError` naming the file and line number.

Parameters honoured
-------------------
* field of view of ``FLASER`` scans, in **degrees**: ``laser_front_laser_fov`` (CARMEN's laser
  module), ``robot_front_laser_fov``, ``laser_laser1_fov``; default 180 degrees. Bearings are
  ``-fov/2 .. +fov/2`` in ``num_readings`` even steps (both edges included); a full 360 degrees
  does not repeat its first beam (step ``fov / num_readings``).
* maximum range, metres: ``robot_front_laser_max`` (CARMEN's robot module),
  ``laser_front_laser_maxrange``, ``laser_front_laser_max_range``, ``robot_front_laser_maxrange``,
  ``laser_laser1_maxrange``, ``laser_laser1_max_range``. Without one, the largest reading in
  the log is taken as the scanner's saturation value.
* mounting offset of the front laser on the robot: ``robot_frontlaser_offset`` (forwards, m),
  ``robot_frontlaser_side_offset`` (to the left, m), ``robot_frontlaser_angular_offset`` (rad);
  default 0.

The first name found in the list wins; ``read_carmen(fov=..., max_range=...)`` overrides both.

Scans
-----
Each laser line becomes a :class:`LaserScan` whose ``odom`` is the pose of the **laser** in the
odometry frame (the robot's odometry composed with the mounting offset), so that the ranges and
``odom`` describe the same sensor. Readings at or beyond the maximum range, zero, negative or
``nan`` readings are *no return* and become ``inf``. ``t`` is the line's last field, the
logger's timestamp.
"""

from __future__ import annotations

import gzip
import io
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from agents.errors import UserError
from agents.files.io import write_atomic
from mapping.se2 import Pose

FloatArray = NDArray[np.float64]

FOV_PARAMS = ("laser_front_laser_fov", "robot_front_laser_fov", "laser_laser1_fov")
MAX_RANGE_PARAMS = (
    "robot_front_laser_max",
    "laser_front_laser_maxrange",
    "laser_front_laser_max_range",
    "robot_front_laser_maxrange",
    "laser_laser1_maxrange",
    "laser_laser1_max_range",
)
OFFSET_PARAMS = ("robot_frontlaser_offset", "robot_frontlaser_side_offset", "robot_frontlaser_angular_offset")
DEFAULT_FOV = math.pi
HOSTNAME = "wiremap"

__all__ = ["CarmenError", "LaserScan", "flaser_angles", "read_carmen", "write_carmen"]


class CarmenError(UserError):
    """A CARMEN log that cannot be read: the message names the file and, for a bad line, its
    number (``log.txt:12: FLASER ...``)."""


@dataclass(frozen=True, eq=False)
class LaserScan:
    """One laser scan of a log.

    Attributes
    ----------
    t : float
        Timestamp in seconds (the log line's last field).
    ranges : (n,) float64
        Range per beam in metres; ``inf`` is no return.
    angles : (n,) float64
        Beam bearings in the laser frame, radians, increasing (counterclockwise).
    max_range : float
        The scanner's maximum range in metres.
    odom : Pose
        The laser's pose in the odometry frame (robot odometry times mounting offset).
    """

    t: float
    ranges: FloatArray
    angles: FloatArray
    max_range: float
    odom: Pose = field(default_factory=Pose)

    def __post_init__(self) -> None:
        r = np.array(self.ranges, dtype=np.float64, copy=True).reshape(-1)
        a = np.array(self.angles, dtype=np.float64, copy=True).reshape(-1)
        if r.shape != a.shape:
            raise ValueError(f"ranges and angles differ in length ({r.size} and {a.size})")
        r.setflags(write=False)
        a.setflags(write=False)
        object.__setattr__(self, "ranges", r)
        object.__setattr__(self, "angles", a)


def flaser_angles(n: int, fov: float) -> FloatArray:
    """Bearings of an ``n``-beam ``FLASER`` scan of field of view ``fov`` radians: ``-fov/2``
    to ``+fov/2`` with both edges, or for a full turn ``n`` steps of ``2 pi / n`` from ``-pi``."""
    if n <= 0:
        return np.zeros(0)
    if n == 1:
        return np.zeros(1)
    if fov >= 2.0 * math.pi - 1e-9:
        return np.asarray(-math.pi + 2.0 * math.pi * np.arange(n) / n, dtype=np.float64)
    return np.linspace(-0.5 * fov, 0.5 * fov, n, dtype=np.float64)


# ---------------------------------------------------------------------------- reading
@dataclass
class _Raw:
    """A laser line before the log-wide parameters are known."""

    line: int
    t: float
    ranges: FloatArray
    angles: FloatArray | None  # None: FLASER, bearings from the fov parameter
    max_range: float | None  # None: the log-wide maximum range
    odom: Pose
    offset: Pose | None  # None: the log-wide mounting offset


class _Line:
    """Token access with errors that name the file and line."""

    def __init__(self, where: str, number: int, tokens: list[str]) -> None:
        self.where, self.number, self.tokens = where, number, tokens
        self.kind = tokens[0]

    def fail(self, why: str) -> CarmenError:
        return CarmenError(f"{self.where}:{self.number}: {self.kind} line {why}")

    def need(self, count: int) -> None:
        if len(self.tokens) < count:
            raise self.fail(f"has {len(self.tokens)} fields, expected at least {count}")

    def num(self, k: int) -> float:
        try:
            v = float(self.tokens[k])
        except (IndexError, ValueError):
            raise self.fail(f"field {k + 1} is not a number: {self.tokens[k]!r}") from None
        if not math.isfinite(v):
            raise self.fail(f"field {k + 1} is not finite: {self.tokens[k]!r}")
        return v

    def count(self, k: int) -> int:
        try:
            v = int(self.tokens[k])
        except (IndexError, ValueError):
            tok = self.tokens[k] if k < len(self.tokens) else "<missing>"
            raise self.fail(f"field {k + 1} is not a count: {tok!r}") from None
        if v < 0:
            raise self.fail(f"field {k + 1} is a negative count: {v}")
        return v

    def nums(self, k: int, n: int) -> FloatArray:
        """``n`` readings from field ``k`` on (``nan`` allowed: no return)."""
        if k + n > len(self.tokens):
            raise self.fail(f"has {len(self.tokens)} fields, too few for {n} readings")
        try:
            return np.asarray(self.tokens[k : k + n], dtype=np.float64)
        except ValueError:
            bad = next(i for i, tok in enumerate(self.tokens[k : k + n]) if not _is_float(tok))
            raise self.fail(f"reading {bad + 1} is not a number: {self.tokens[k + bad]!r}") from None

    def pose(self, k: int) -> Pose:
        return Pose(self.num(k), self.num(k + 1), self.num(k + 2))


def _is_float(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _open_text(path: Path) -> io.TextIOBase:
    if path.suffix == ".gz":
        return io.TextIOWrapper(gzip.open(path, "rb"), encoding="utf-8", errors="replace")
    return open(path, encoding="utf-8", errors="replace")


def read_carmen(
    path: str | os.PathLike[str], *, fov: float | None = None, max_range: float | None = None
) -> list[LaserScan]:
    """All laser scans of a CARMEN log, in file order (see the module notes for the format).

    Parameters
    ----------
    path : str or path-like
        The log (``.gz`` is decompressed).
    fov : float, optional
        Field of view of ``FLASER`` scans in radians, overriding the log's parameters.
    max_range : float, optional
        Maximum range in metres, overriding the log's parameters and each line's own.

    Returns
    -------
    list of LaserScan

    Raises
    ------
    CarmenError
        When the file cannot be read, or a line of a type read here is malformed (the message
        gives the line number), or a parameter honoured here is not a number.
    """
    p = Path(path)
    where = str(path)
    params: dict[str, tuple[int, str]] = {}
    raws: list[_Raw] = []
    last_odom: Pose | None = None
    try:
        fh = _open_text(p)
    except FileNotFoundError:
        raise CarmenError(f"{where}: no such file") from None
    except OSError as exc:
        raise CarmenError(f"{where}: {exc.strerror or exc}") from None
    try:
        with fh:
            for number, text in enumerate(fh, start=1):
                tokens = text.split()
                if not tokens or tokens[0].startswith("#"):
                    continue
                kind = tokens[0]
                if kind == "PARAM":
                    if len(tokens) >= 3:
                        params.setdefault(tokens[1], (number, " ".join(tokens[2:])))
                    continue
                if kind not in ("FLASER", "ROBOTLASER1", "RAWLASER1", "ODOM"):
                    continue
                ln = _Line(where, number, tokens)
                if kind == "ODOM":
                    ln.need(4)
                    last_odom = ln.pose(1)
                    continue
                raw = _parse_laser(ln, last_odom)
                if raw is not None:
                    raws.append(raw)
    except (OSError, EOFError, gzip.BadGzipFile) as exc:
        raise CarmenError(f"{where}: cannot read: {exc}") from None

    def param(names: tuple[str, ...]) -> float | None:
        for name in names:
            if name in params:
                number, value = params[name]
                try:
                    v = float(value)
                except ValueError:
                    raise CarmenError(f"{where}:{number}: PARAM {name} is not a number: {value!r}") from None
                if not math.isfinite(v):
                    raise CarmenError(f"{where}:{number}: PARAM {name} is not finite: {value!r}")
                return v
        return None

    if fov is None:
        fov_deg = param(FOV_PARAMS)
        fov = DEFAULT_FOV if fov_deg is None else math.radians(fov_deg)
    if not (0.0 < fov <= 2.0 * math.pi + 1e-9):
        raise CarmenError(f"{where}: laser field of view {math.degrees(fov):g} degrees is outside (0, 360]")
    log_max = max_range if max_range is not None else param(MAX_RANGE_PARAMS)
    if log_max is None:
        finite = [float(np.nanmax(r.ranges)) for r in raws if r.ranges.size and np.any(np.isfinite(r.ranges))]
        log_max = max(finite) if finite else math.inf
    if not log_max > 0.0:
        raise CarmenError(f"{where}: maximum laser range {log_max:g} m is not positive")
    fwd, side, ang = (param((name,)) or 0.0 for name in OFFSET_PARAMS)
    log_offset = Pose(fwd, side, ang)

    scans: list[LaserScan] = []
    for raw in raws:
        angles = raw.angles if raw.angles is not None else flaser_angles(raw.ranges.size, fov)
        rmax = max_range if max_range is not None else (raw.max_range or log_max)
        ranges = raw.ranges.copy()
        with np.errstate(invalid="ignore"):
            ranges[~(ranges > 0.0) | (ranges >= rmax)] = np.inf
        offset = raw.offset if raw.offset is not None else log_offset
        scans.append(LaserScan(raw.t, ranges, angles, float(rmax), raw.odom.compose(offset)))
    return scans


def _parse_laser(ln: _Line, last_odom: Pose | None) -> _Raw | None:
    tok = ln.tokens
    if ln.kind == "FLASER":
        ln.need(2)
        n = ln.count(1)
        # n readings, 6 pose numbers, then "ipc_timestamp hostname logger_timestamp" (current)
        # or a single timestamp (old logs).
        if len(tok) not in (2 + n + 6 + 3, 2 + n + 6 + 1):
            raise ln.fail(f"has {len(tok)} fields, expected {2 + n + 9} for {n} readings")
        ranges = ln.nums(2, n)
        ln.pose(2 + n)  # the logged laser pose: checked, not used
        odom = ln.pose(2 + n + 3)
        t = ln.num(len(tok) - 1)
        return _Raw(ln.number, t, ranges, None, None, odom, None)
    # ROBOTLASER1 / RAWLASER1 share their first fields.
    ln.need(9)
    start, _fov, res, rmax = ln.num(2), ln.num(3), ln.num(4), ln.num(5)
    n = ln.count(8)
    ranges = ln.nums(9, n)
    k = 9 + n
    ln.need(k + 1)
    n_rem = ln.count(k)
    k += 1 + n_rem
    angles = start + res * np.arange(n, dtype=np.float64)
    if n > 1 and not res > 0.0:
        raise ln.fail(f"has a non-positive angular resolution {res:g}")
    if ln.kind == "ROBOTLASER1":
        expected = k + 6 + 5 + 3
        if len(tok) != expected:
            raise ln.fail(f"has {len(tok)} fields, expected {expected} for {n} readings and {n_rem} remissions")
        laser = ln.pose(k)
        robot = ln.pose(k + 3)
        t = ln.num(len(tok) - 1)
        return _Raw(ln.number, t, ranges, angles, rmax if rmax > 0 else None, robot, robot.between(laser))
    expected = k + 3
    if len(tok) != expected:
        raise ln.fail(f"has {len(tok)} fields, expected {expected} for {n} readings and {n_rem} remissions")
    t = ln.num(len(tok) - 1)
    if last_odom is None:
        return None  # no odometry yet
    return _Raw(ln.number, t, ranges, angles, rmax if rmax > 0 else None, last_odom, None)


# ---------------------------------------------------------------------------- writing
def write_carmen(
    path: str | os.PathLike[str],
    scans: Iterable[LaserScan],
    *,
    fov: float,
    max_range: float,
    comment: str | None = None,
) -> int:
    """Write scans as a CARMEN log, atomically: ``PARAM`` lines for the field of view
    (``laser_front_laser_fov``, degrees) and the maximum range (``robot_front_laser_max``),
    then one ``FLASER`` line per scan with its ``odom`` in both pose slots (the simulator's
    laser sits at the robot's centre), hostname ``wiremap`` and ``t`` as both timestamps.

    Ranges are written with 4 decimals (0.1 mm), poses with 6; no return (``inf``, ``nan``,
    ``>= max_range``) is written as ``max_range``, and a return that would print as
    ``max_range`` is written just below it, so that reading gives back the same returns.

    Parameters
    ----------
    path : str or path-like
    scans : iterable of LaserScan
        Their bearings must be :func:`flaser_angles` of their length and ``fov``.
    fov : float
        Field of view in radians, ``(0, 2 pi]``.
    max_range : float
        Maximum range in metres (positive, finite).
    comment : str, optional
        Written as ``#`` lines at the top.

    Returns
    -------
    int
        The number of scans written.

    Raises
    ------
    ValueError
        For a bad ``fov`` or ``max_range``, or a scan whose bearings do not match ``fov``.
    """
    if not (math.isfinite(fov) and 0.0 < fov <= 2.0 * math.pi + 1e-9):
        raise ValueError(f"fov must be in (0, 2*pi] radians, got {fov}")
    if not (math.isfinite(max_range) and max_range > 0.0):
        raise ValueError(f"max_range must be a positive number of metres, got {max_range}")
    out = io.StringIO()
    for line in (comment or "").splitlines():
        out.write(f"# {line}\n")
    out.write("# written by wiremap: FLASER odometry poses in both pose slots\n")
    out.write(f"PARAM laser_front_laser_fov {math.degrees(fov):.6f}\n")
    out.write(f"PARAM robot_front_laser_max {max_range:.6f}\n")
    below = max_range - 1e-4  # the largest value that prints below max_range at 4 decimals
    count = 0
    for k, s in enumerate(scans):
        n = s.ranges.size
        if not np.allclose(s.angles, flaser_angles(n, fov), atol=1e-9):
            raise ValueError(f"scan {k}: its {n} bearings are not the FLASER bearings of a {fov:g} rad field of view")
        r = np.asarray(s.ranges, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            miss = ~np.isfinite(r) | (r >= max_range) | ~(r > 0.0)
        r = np.where(miss, max_range, np.minimum(r, below))
        text = " ".join(f"{v:.4f}" for v in r.tolist())
        o = s.odom
        pose = f"{o.x:.6f} {o.y:.6f} {o.theta:.6f}"
        out.write(f"FLASER {n} {text} {pose} {pose} {s.t:.6f} {HOSTNAME} {s.t:.6f}\n")
        count += 1
    write_atomic(path, out.getvalue())
    return count
