"""CARMEN log files: read real laser scans with odometry, write simulated ones.

CARMEN logs are text, one message per line, the message type first. This module reads the
laser, odometry and true-pose messages and the parameters that describe the scanners, from
logs as robots wrote them (plain or gzip'd, whatever the suffix; CRLF line ends; a truncated
last line), and writes logs that CARMEN tools (and this reader) understand.

Messages read
-------------
Each laser line ends in its time: ``ipc_timestamp hostname logger_timestamp`` (current logs) or
a single ``timestamp`` (old logs). ``t`` of a scan is the last one (the logger's timestamp).

``FLASER num_readings [range_readings] x y theta odom_x odom_y odom_theta <time>``
    The front laser (``RLASER``: the rear laser, same fields). ``x y theta`` is the laser's pose
    *as the logger knew it* -- in corrected logs a pose estimate, never a measurement -- so it
    is checked but ignored; the **odometry** ``odom_x odom_y odom_theta`` is used. When the two
    triples are equal (corrected logs, and logs whose odometry was rewritten from them, such as
    the shared Radish logs), the odometry is the *laser's* pose already and the mounting offset
    is not composed again: ``mount`` is the identity for that line.
``ROBOTLASER1 laser_type start_angle field_of_view angular_resolution maximum_range accuracy
remission_mode num_readings [range_readings] num_remissions [remissions] laser_x laser_y
laser_theta robot_x robot_y robot_theta tv rv forward_safety side_safety turn_axis <time>``
    A laser with its own geometry (``ROBOTLASER2`` likewise): bearings ``start_angle + k *
    angular_resolution``, its own ``maximum_range`` (when positive). The odometry is ``robot_x
    robot_y robot_theta``; the laser's mounting offset is ``robot^-1 * laser`` from the same
    line. Old lines without the five ``tv .. turn_axis`` fields are accepted.
``RAWLASER1 .. RAWLASER4 laser_type start_angle field_of_view angular_resolution maximum_range
accuracy remission_mode num_readings [range_readings] num_remissions [remissions] <time>``
    A laser without a pose: its odometry is that of the latest ``ODOM`` line before it (scans
    before the first ``ODOM`` are skipped).
``ODOM x y theta tv rv accel <time>``
    Robot odometry. **Which wins:** a laser line that carries an odometry pose uses its own,
    which the logger recorded for the scan's time; ``ODOM`` lines are used only for
    ``RAWLASER`` scans, which carry none.
``TRUEPOS true_x true_y true_theta odom_x odom_y odom_theta <time>``
    The robot's true pose (simulators): kept as :attr:`CarmenLog.truepos`.
``PARAM name value [hostname timestamp]``
    Parameters, wherever they appear in the file; the first line of a name wins.

Every other message type (``NMEAGGA``, ``NEFF``, ``SYNC``, ...) is skipped, as are empty lines
and lines starting with ``#``.

Laser streams
-------------
A log may hold several lasers; one stream is mapped: the ``laser`` argument, by default the
first of :data:`LASERS` that occurs in the log (``FLASER`` before ``ROBOTLASER1`` before
``RAWLASER1`` before the rear lasers).

Unreadable lines
----------------
A line of a type read here that cannot be read (a field that is not a number, a pose that is
``nan``, a wrong field count, a truncated last line) is an *issue* naming the file and line
(``log.txt:12: FLASER line has 40 fields, ...``). With ``strict=True`` the first issue raises
:class:`CarmenError`; otherwise the line is skipped and the issue kept in
:attr:`CarmenLog.issues`. A skipped laser line still counts in :attr:`LaserScan.index`, so
that per-scan files (one truth row per ``FLASER`` line) stay aligned.

Parameters honoured
-------------------
For the front laser (``FLASER``; ``RLASER`` reads the same names with ``rear`` for ``front``):

* field of view in **degrees**: ``laser_front_laser_fov``, ``robot_front_laser_fov``: bearings
  ``-fov/2 .. +fov/2`` in ``num_readings`` even steps (both edges included); a full 360 degrees
  does not repeat its first beam (step ``fov / num_readings``).
* else the angular resolution in degrees, ``laser_front_laser_resolution``; else the standard
  resolution (1, 0.5 or 0.25 degrees) within 2 % of ``180 / (num_readings - 1)``, so that 181
  beams are 1 degree apart and 180 too (a 1-degree scanner that logs 180 readings; spread over
  180 degrees its turns come out 0.3 % too large, which the matcher then carries around every
  loop); else 180 degrees over the beams.
  The first beam is at -90 degrees, as CARMEN's own reader has it (``start_angle = -pi/2``):
  180 beams span -90 .. +89 degrees (:func:`carmen_bearings`).
* maximum range, metres: ``robot_front_laser_max`` (CARMEN's robot module),
  ``laser_front_laser_maxrange``, ``laser_front_laser_max_range``,
  ``robot_front_laser_maxrange``. Without one, the largest reading of the stream is taken as
  the scanner's saturation value.
* mounting offset on the robot: ``robot_frontlaser_offset`` (forwards, m),
  ``robot_frontlaser_side_offset`` (to the left, m), ``robot_frontlaser_angular_offset``
  (rad); default 0. The rear laser faces backwards (angular offset ``pi`` added).
* seconds from one beam to the next, ``wiremap_front_laser_time_increment`` (wiremap's own, as
  ROS's ``LaserScan.time_increment``; :func:`write_carmen` writes it for a scanner whose beams
  are not simultaneous, a spinning lidar's; CARMEN has none, and without it, or when a scan's
  beams would take over ``MAX_SWEEP`` (1 s) by it, the beams are taken as simultaneous): the
  line's timestamp is its first beam's.

The first name found in the list wins; ``fov=`` and ``max_range=`` arguments override them. A
parameter honoured here whose value is not a number is an issue (see above) and is ignored.

Scans
-----
Each laser line becomes a :class:`LaserScan` whose ``odom`` is the pose of the **laser** in the
odometry frame (the robot's odometry composed with ``mount``, the mounting offset), so that the
ranges and ``odom`` describe the same sensor. Readings at or beyond the maximum range, zero,
negative, ``nan`` or ``inf`` readings are *no return* and become ``inf``.
"""

from __future__ import annotations

import gzip
import io
import math
import os
import re
import zlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from agents.errors import UserError
from agents.files.io import is_number, write_atomic
from mapping.se2 import Pose

FloatArray = NDArray[np.float64]

#: Laser message types, in the order a stream is chosen by default.
LASERS = (
    "FLASER", "ROBOTLASER1", "RAWLASER1", "RLASER", "ROBOTLASER2", "RAWLASER2", "RAWLASER3", "RAWLASER4",
)
#: Message types read (everything else is skipped).
MESSAGES = (*LASERS, "ODOM", "TRUEPOS", "PARAM")
FOV_PARAMS = ("laser_front_laser_fov", "robot_front_laser_fov")
RESOLUTION_PARAMS = ("laser_front_laser_resolution",)
MAX_RANGE_PARAMS = (
    "robot_front_laser_max",
    "laser_front_laser_maxrange",
    "laser_front_laser_max_range",
    "robot_front_laser_maxrange",
)
OFFSET_PARAMS = ("robot_frontlaser_offset", "robot_frontlaser_side_offset", "robot_frontlaser_angular_offset")
TIME_INCREMENT_PARAMS = ("wiremap_front_laser_time_increment",)
#: A scan whose beams would take longer than this (seconds) by its time increment is taken as
#: simultaneous (0): no planar lidar takes a second for a scan, and a wrong value should not
#: bend the scan (the ROS bag reader and the live robot apply the same limit).
MAX_SWEEP = 1.0


def beam_time_increment(dt: float, beams: int) -> float:
    """A scan's time from one beam to the next as read: ``dt``, or 0 (simultaneous beams) when it
    is not a number or its ``beams`` would take longer than ``MAX_SWEEP``."""
    return dt if math.isfinite(dt) and sweep_seconds(dt, beams) <= MAX_SWEEP else 0.0


def sweep_seconds(dt: float, beams: int) -> float:
    """Seconds from a scan's first beam to its last, its ``beams`` ``dt`` apart."""
    return abs(dt) * max(beams - 1, 0)
DEFAULT_FOV = math.pi
HOSTNAME = "wiremap"
_MESSAGE_TYPE = re.compile(r"[A-Z][A-Z0-9_]*\Z")

__all__ = [
    "LASERS",
    "MAX_SWEEP",
    "CarmenError",
    "CarmenLog",
    "LaserScan",
    "beam_time_increment",
    "carmen_bearings",
    "flaser_angles",
    "read_carmen",
    "read_carmen_log",
    "read_truth_tsv",
    "scan_truth",
    "sweep_seconds",
    "truth_path_for",
    "write_carmen",
]


class CarmenError(UserError):
    """A CARMEN log that cannot be read: the message names the file and, for a bad line, its
    number (``log.txt:12: FLASER ...``)."""


@dataclass(frozen=True, eq=False)
class LaserScan:
    """One laser scan of a log.

    Attributes
    ----------
    t : float
        Timestamp in seconds (the line's logger timestamp, else its last timestamp).
    ranges : (n,) float64
        Range per beam in metres; ``inf`` is no return.
    angles : (n,) float64
        Beam bearings in the laser frame, radians, increasing (counterclockwise).
    max_range : float
        The scanner's maximum range in metres.
    odom : Pose
        The laser's pose in the odometry frame (robot odometry times ``mount``).
    mount : Pose
        The laser's pose on the robot (its mounting offset).
    kind : str
        The message type (``"FLASER"``, ...).
    index : int
        0-based number of the line among the log's lines of ``kind``, unreadable ones included.
    time_increment : float
        Seconds from one beam to the next in the order of ``angles`` (negative: the last beam
        first), ROS's ``LaserScan.time_increment``; ``t`` is the first beam's time. 0: the beams
        are taken as simultaneous.
    odom_end : Pose or None
        The laser's pose in the odometry frame at the last beam's time (``t`` plus
        :attr:`sweep`), when the reader had odometry then (a bag's or a live robot's odometry
        stream); None otherwise (a CARMEN log: the de-skew takes the wheels' motion to the next
        scan, :func:`agents.mapping_run.deskewed`).
    """

    t: float
    ranges: FloatArray
    angles: FloatArray
    max_range: float
    odom: Pose = field(default_factory=Pose)
    mount: Pose = field(default_factory=Pose)
    kind: str = "FLASER"
    index: int = 0
    time_increment: float = 0.0
    odom_end: Pose | None = None

    @property
    def sweep(self) -> float:
        """Seconds from the first beam to the last (0: simultaneous beams)."""
        return sweep_seconds(self.time_increment, self.angles.size)

    def __post_init__(self) -> None:
        r = np.array(self.ranges, dtype=np.float64, copy=True).reshape(-1)
        a = np.array(self.angles, dtype=np.float64, copy=True).reshape(-1)
        if r.shape != a.shape:
            raise ValueError(f"ranges and angles differ in length ({r.size} and {a.size})")
        r.setflags(write=False)
        a.setflags(write=False)
        object.__setattr__(self, "ranges", r)
        object.__setattr__(self, "angles", a)


@dataclass
class CarmenLog:
    """What :func:`read_carmen_log` found in a log.

    Attributes
    ----------
    path : str
    scans : list of LaserScan
        The chosen laser stream's scans, in file order.
    laser : str or None
        The chosen stream's message type (None: the log has no laser lines).
    lasers : dict of str to int
        Lines per laser message type (unreadable ones included).
    truepos : list of (float, Pose)
        ``(t, true robot pose)`` of each ``TRUEPOS`` line.
    issues : list of str
        One message per skipped unreadable line (``path:line: ...``).
    params : dict of str to str
        Every ``PARAM`` (first line of a name wins), value without host and timestamp.
    """

    path: str
    scans: list[LaserScan]
    laser: str | None
    lasers: dict[str, int]
    truepos: list[tuple[float, Pose]]
    issues: list[str]
    params: dict[str, str]


#: Angular resolutions (degrees) planar scanners step in, for a log that names neither its field
#: of view nor its resolution (module notes, "Parameters honoured").
STANDARD_RESOLUTIONS_DEG = (1.0, 0.5, 0.25)


def default_width(n: int) -> float:
    """The field of view (radians) of an ``n``-beam scan whose log gives no geometry: the
    standard resolution within 2 % of ``180 / (n - 1)`` degrees times ``n - 1``, else 180
    degrees."""
    if n < 2:
        return DEFAULT_FOV
    guess = 180.0 / (n - 1)
    res = min(STANDARD_RESOLUTIONS_DEG, key=lambda r: abs(r - guess))
    if abs(res - guess) > 0.02 * res:
        return DEFAULT_FOV
    return math.radians(res * (n - 1))


def carmen_bearings(n: int, width: float) -> FloatArray:
    """Bearings of an ``n``-beam scan whose log gives its resolution (or none) but no field of
    view, ``width`` radians from the first beam to the last. A half-turn scanner short of at
    most one beam starts at -90 degrees, as CARMEN's own reader lays it (``start_angle =
    -pi/2``): 180 beams 1 degree apart span -90 .. +89 degrees (CARMEN: "last beam ignored"),
    not -89.5 .. +89.5. Centred, every such scan is turned half a beam and so is every motion
    the matcher measures (docs/experiments.md, "Where a 180-beam scan starts"). Any other width
    is centred (:func:`flaser_angles`)."""
    if n < 2 or width >= 2.0 * math.pi - 1e-9:
        return flaser_angles(n, width)
    step = width / (n - 1)
    if math.pi - width > step + 1e-9:
        return flaser_angles(n, width)
    return np.asarray(-0.5 * math.pi + step * np.arange(n), dtype=np.float64)


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

    kind: str
    index: int
    t: float
    ranges: FloatArray
    angles: FloatArray | None  # None: FLASER/RLASER, bearings from the parameters
    max_range: float | None  # None: the stream's maximum range
    odom: Pose
    mount: Pose | None  # None: the stream's mounting offset


class _Line:
    """Token access with errors that name the file and line."""

    def __init__(self, where: str, number: int, tokens: list[str], truncated: bool) -> None:
        self.where, self.number, self.tokens = where, number, tokens
        self.kind = tokens[0]
        self.truncated = truncated

    def fail(self, why: str) -> CarmenError:
        tail = " (truncated last line)" if self.truncated else ""
        return CarmenError(f"{self.where}:{self.number}: {self.kind} line {why}{tail}")

    def need(self, count: int) -> None:
        if len(self.tokens) < count:
            raise self.fail(f"has {len(self.tokens)} fields, expected at least {count}")

    def num(self, k: int) -> float:
        tok = self.tokens[k] if k < len(self.tokens) else "<missing>"
        try:
            v = float(tok)
        except ValueError:
            raise self.fail(f"field {k + 1} is not a number: {tok!r}") from None
        if not math.isfinite(v):
            raise self.fail(f"field {k + 1} is not finite: {tok!r}")
        return v

    def count(self, k: int) -> int:
        tok = self.tokens[k] if k < len(self.tokens) else "<missing>"
        try:
            v = int(tok)
        except ValueError:
            raise self.fail(f"field {k + 1} is not a count: {tok!r}") from None
        if v < 0:
            raise self.fail(f"field {k + 1} is a negative count: {v}")
        return v

    def nums(self, k: int, n: int) -> FloatArray:
        """``n`` readings from field ``k`` on (``nan`` and ``inf`` allowed: no return)."""
        if k + n > len(self.tokens):
            raise self.fail(f"has {len(self.tokens)} fields, too few for {n} readings")
        try:
            return np.asarray(self.tokens[k : k + n], dtype=np.float64)
        except ValueError:
            bad = next(i for i, tok in enumerate(self.tokens[k : k + n]) if not is_number(tok))
            raise self.fail(f"reading {bad + 1} is not a number: {self.tokens[k + bad]!r}") from None

    def pose(self, k: int) -> Pose:
        return Pose(self.num(k), self.num(k + 1), self.num(k + 2))

    def stamp(self, first: int) -> float:
        """The time of a line whose time fields start at ``first``: ``timestamp`` (old logs) or
        ``ipc_timestamp hostname logger_timestamp`` (the logger's)."""
        rest = len(self.tokens) - first
        return self.num(first + (2 if rest == 3 else 0))



def _open_text(path: Path) -> io.TextIOBase:
    """The file as text: gzip'd or not by its first bytes, not its name; newline="" keeps CRLF
    out of the way (``split`` drops the ``\\r``)."""
    with open(path, "rb") as fh:
        magic = fh.read(2)
    if magic == b"\x1f\x8b":
        return io.TextIOWrapper(gzip.open(path, "rb"), encoding="utf-8", errors="replace", newline="")
    return open(path, encoding="utf-8", errors="replace", newline="")


def _param_value(tokens: list[str]) -> str:
    """The value of ``PARAM name value [hostname timestamp]``: a trailing pair whose last field
    is a number is the host and timestamp (``PARAM robot_front_laser_max 80.99 nohost 0``)."""
    vals = tokens[2:]
    if len(vals) >= 3 and is_number(vals[-1]):
        vals = vals[:-2]
    return " ".join(vals)


def _names(names: tuple[str, ...], kind: str) -> tuple[str, ...]:
    """Parameter names for the stream ``kind``: the rear laser's are the front's with ``rear``."""
    if kind in ("RLASER", "ROBOTLASER2"):
        return tuple(n.replace("front", "rear") for n in names)
    return names


def read_carmen_log(
    path: str | os.PathLike[str],
    *,
    strict: bool = False,
    fov: float | None = None,
    max_range: float | None = None,
    laser: str | None = None,
) -> CarmenLog:
    """Read a CARMEN log (see the module notes for the format).

    Parameters
    ----------
    path : str or path-like
        The log, plain text or gzip'd (recognised by its first bytes).
    strict : bool
        Raise on the first unreadable line instead of skipping it.
    fov : float, optional
        Field of view of ``FLASER``/``RLASER`` scans in radians, overriding the parameters.
    max_range : float, optional
        Maximum range in metres, overriding the log's parameters and each line's own.
    laser : str, optional
        The laser stream to read (one of :data:`LASERS`); default the first present.

    Returns
    -------
    CarmenLog

    Raises
    ------
    CarmenError
        When the file is missing or unreadable, is not a CARMEN log or a corrupt gzip file;
        with ``strict``, for the first unreadable line or parameter.
    """
    if laser is not None and laser not in LASERS:
        raise CarmenError(f"unknown laser message type {laser!r}; one of {', '.join(LASERS)}")
    log = _Collected(str(path), strict, laser)
    _read_lines(Path(path), log)
    laser, raws = _choose_stream(log)
    geometry = _stream_geometry(log, laser or "FLASER", raws, fov, max_range)
    scans = [_to_scan(raw, geometry, max_range) for raw in raws]
    return _summary(log, scans, laser)


@dataclass
class _Collected:
    """What one pass over a log's lines collects, before a stream is chosen and its parameters
    applied; ``issue`` keeps (or, with ``strict``, raises) an unreadable line or parameter."""

    where: str
    strict: bool
    laser: str | None  # the stream asked for; None: every laser line is kept until the choice
    params: dict[str, tuple[int, str]] = field(default_factory=dict)  # name -> (line, value)
    raws: list[_Raw] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    truepos: list[tuple[float, Pose]] = field(default_factory=list)
    issues: list[str] = field(default_factory=list)
    last_odom: Pose | None = None
    seen_message: bool = False

    def issue(self, err: CarmenError) -> None:
        if self.strict:
            raise err
        self.issues.append(str(err))


def _read_lines(path: Path, log: _Collected) -> None:
    """Open the log and read every line into ``log``; opening and reading errors become
    :class:`CarmenError` naming the file."""
    where = log.where
    try:
        fh = _open_text(path)
    except FileNotFoundError:
        raise CarmenError(f"{where}: no such file") from None
    except IsADirectoryError:
        raise CarmenError(f"{where}: is a directory, not a log") from None
    except OSError as exc:
        raise CarmenError(f"{where}: {exc.strerror or exc}") from None
    try:
        with fh:
            for number, text in enumerate(fh, start=1):
                _read_line(log, number, text)
    except (EOFError, gzip.BadGzipFile, zlib.error) as exc:
        raise CarmenError(f"{where}: corrupt or truncated gzip file: {exc}") from None
    except OSError as exc:
        raise CarmenError(f"{where}: cannot read: {exc}") from None


def _read_line(log: _Collected, number: int, text: str) -> None:
    """One line: comments and blank lines skipped, the first message line checked for a message
    type, ``PARAM`` kept (the first line of a name wins), laser lines counted per type and those
    of other streams than ``log.laser`` skipped, the rest parsed (:func:`_read_message`)."""
    tokens = text.split()
    if not tokens or tokens[0].startswith("#"):
        return
    kind = tokens[0]
    if not log.seen_message:
        if not _MESSAGE_TYPE.match(kind) or "\ufffd" in text:
            raise CarmenError(
                f"{log.where}: not a CARMEN log (line {number} does not start with a message type)"
            )
        log.seen_message = True
    if kind == "PARAM":
        if len(tokens) >= 3:
            log.params.setdefault(tokens[1], (number, _param_value(tokens)))
        return
    if kind not in MESSAGES:
        return
    ln = _Line(log.where, number, tokens, truncated=not text.endswith("\n"))
    index = 0  # the line's number among its type's (laser lines only)
    if kind in LASERS:
        index = log.counts.get(kind, 0)
        log.counts[kind] = index + 1
        if log.laser is not None and kind != log.laser:
            return
    try:
        _read_message(log, ln, index)
    except CarmenError as err:
        log.issue(err)


def _read_message(log: _Collected, ln: _Line, index: int) -> None:
    """Parse an ``ODOM``, ``TRUEPOS`` or laser line into ``log`` (raises :class:`CarmenError`
    for an unreadable one); a laser line's ``index`` is its number among its type's lines."""
    if ln.kind == "ODOM":
        ln.need(8)
        log.last_odom = ln.pose(1)
    elif ln.kind == "TRUEPOS":
        ln.need(8)
        log.truepos.append((ln.stamp(7), ln.pose(1)))
    else:
        raw = _parse_laser(ln, index, log.last_odom)
        if raw is not None:
            log.raws.append(raw)


def _choose_stream(log: _Collected) -> tuple[str | None, list[_Raw]]:
    """The stream mapped (``log.laser``, else the first of :data:`LASERS` present; None without
    laser lines) and its lines."""
    laser = log.laser
    if laser is None:
        laser = next((k for k in LASERS if log.counts.get(k)), None)
    return laser, [r for r in log.raws if r.kind == laser]


def _param(log: _Collected, names: tuple[str, ...]) -> float | None:
    """The first of ``names`` among the log's parameters that is a finite number; one that is
    not is an issue and is passed over."""
    for name in names:
        if name in log.params:
            number, value = log.params[name]
            try:
                v = float(value)
            except ValueError:
                log.issue(CarmenError(f"{log.where}:{number}: PARAM {name} is not a number: {value!r}"))
                continue
            if not math.isfinite(v):
                log.issue(CarmenError(f"{log.where}:{number}: PARAM {name} is not finite: {value!r}"))
                continue
            return v
    return None


@dataclass(frozen=True)
class _Geometry:
    """A stream's scanner geometry from the parameters and the arguments."""

    fov_deg: float | None  # field of view, degrees
    res_deg: float | None  # angular resolution, degrees (only without a field of view)
    log_max: float  # maximum range, metres
    mount: Pose  # mounting offset on the robot
    time_increment: float = 0.0  # seconds from one beam to the next


def _stream_geometry(
    log: _Collected, kind: str, raws: list[_Raw], fov: float | None, max_range: float | None
) -> _Geometry:
    """The parameters honoured for the stream ``kind`` (module notes), ``fov`` and ``max_range``
    overriding them; without a maximum range, the largest finite reading of ``raws``."""
    where = log.where
    fov_deg = _param(log, _names(FOV_PARAMS, kind))
    res_deg = _param(log, _names(RESOLUTION_PARAMS, kind)) if fov_deg is None else None
    if fov is not None:
        fov_deg = math.degrees(fov)
    if fov_deg is not None and not (0.0 < fov_deg <= 360.0 + 1e-7):
        raise CarmenError(f"{where}: laser field of view {fov_deg:g} degrees is outside (0, 360]")
    log_max = max_range if max_range is not None else _param(log, _names(MAX_RANGE_PARAMS, kind))
    if log_max is None:
        finite = [float(np.max(r.ranges[np.isfinite(r.ranges)])) for r in raws if np.isfinite(r.ranges).any()]
        log_max = max(finite) if finite else math.inf
    if not log_max > 0.0:
        raise CarmenError(f"{where}: maximum laser range {log_max:g} m is not positive")
    fwd, side, ang = (_param(log, (name,)) or 0.0 for name in _names(OFFSET_PARAMS, kind))
    stream_mount = Pose(fwd, side, ang + (math.pi if kind == "RLASER" else 0.0))
    dt = _param(log, _names(TIME_INCREMENT_PARAMS, kind)) or 0.0
    return _Geometry(fov_deg, res_deg, log_max, stream_mount, dt)


def _to_scan(raw: _Raw, geometry: _Geometry, max_range: float | None) -> LaserScan:
    """A laser line as a :class:`LaserScan`: bearings from the line or the stream's geometry,
    no-return readings as ``inf``, the odometry composed with the mounting offset."""
    angles = raw.angles
    if angles is None:
        n = raw.ranges.size
        if geometry.fov_deg is not None:
            angles = flaser_angles(n, math.radians(geometry.fov_deg))
        elif geometry.res_deg is not None and 0.0 < geometry.res_deg * (n - 1) <= 360.0:
            angles = carmen_bearings(n, math.radians(geometry.res_deg * (n - 1)))
        else:
            angles = carmen_bearings(n, default_width(n))
    rmax = max_range if max_range is not None else (raw.max_range or geometry.log_max)
    ranges = raw.ranges.copy()
    with np.errstate(invalid="ignore"):
        ranges[~(ranges > 0.0) | (ranges >= rmax)] = np.inf
    mount = raw.mount if raw.mount is not None else geometry.mount
    return LaserScan(raw.t, ranges, angles, float(rmax), raw.odom.compose(mount), mount, raw.kind, raw.index,
                     beam_time_increment(geometry.time_increment, ranges.size))


def _summary(log: _Collected, scans: list[LaserScan], laser: str | None) -> CarmenLog:
    """The :class:`CarmenLog` of the chosen stream's scans and what the pass collected."""
    values = {name: value for name, (_, value) in log.params.items()}
    return CarmenLog(log.where, scans, laser, log.counts, log.truepos, log.issues, values)


def read_carmen(
    path: str | os.PathLike[str],
    *,
    fov: float | None = None,
    max_range: float | None = None,
    strict: bool = True,
    laser: str | None = None,
) -> list[LaserScan]:
    """The scans of one laser stream of a CARMEN log, in file order: :func:`read_carmen_log`
    (strict by default) without the rest.

    Raises
    ------
    CarmenError
        See :func:`read_carmen_log`.
    """
    return read_carmen_log(path, strict=strict, fov=fov, max_range=max_range, laser=laser).scans


def _parse_laser(ln: _Line, index: int, last_odom: Pose | None) -> _Raw | None:
    tok = ln.tokens
    if ln.kind in ("FLASER", "RLASER"):
        ln.need(2)
        n = ln.count(1)
        # n readings, 6 pose numbers, then 1 to 3 time fields.
        rest = len(tok) - 2 - n
        if rest not in (7, 9):
            raise ln.fail(f"has {len(tok)} fields, expected {2 + n + 9} for {n} readings")
        ranges = ln.nums(2, n)
        logged = ln.pose(2 + n)
        odom = ln.pose(2 + n + 3)
        # Equal pose triples: the odometry slot holds the laser's own pose (see the notes).
        mount = Pose() if logged.almost_equal(odom, tol=1e-6, angle_tol=1e-6) else None
        return _Raw(ln.kind, index, ln.stamp(2 + n + 6), ranges, None, None, odom, mount)
    # ROBOTLASER / RAWLASER share their first fields.
    ln.need(10)
    start, res, rmax = ln.num(2), ln.num(4), ln.num(5)
    n = ln.count(8)
    ranges = ln.nums(9, n)
    k = 9 + n
    ln.need(k + 1)
    n_rem = ln.count(k)
    k += 1 + n_rem
    ln.need(k)
    angles = start + res * np.arange(n, dtype=np.float64)
    if n > 1 and not res > 0.0:
        raise ln.fail(f"has a non-positive angular resolution {res:g}")
    rest = len(tok) - k
    if ln.kind.startswith("ROBOTLASER"):
        if rest not in (7, 9, 12, 14):
            raise ln.fail(f"has {len(tok)} fields, expected {k + 14} for {n} readings and {n_rem} remissions")
        laser = ln.pose(k)
        robot = ln.pose(k + 3)
        t = ln.stamp(k + (11 if rest >= 12 else 6))
        return _Raw(ln.kind, index, t, ranges, angles, rmax if rmax > 0 else None, robot,
                    robot.between(laser))
    if rest not in (1, 3):
        raise ln.fail(f"has {len(tok)} fields, expected {k + 3} for {n} readings and {n_rem} remissions")
    t = ln.stamp(k)
    if last_odom is None:
        return None  # no odometry yet
    return _Raw(ln.kind, index, t, ranges, angles, rmax if rmax > 0 else None, last_odom, None)


# ---------------------------------------------------------------------------- truth
def truth_path_for(log: str | os.PathLike[str]) -> Path:
    """Where a log's truth file sits: ``NAME.truth.tsv`` beside ``NAME.log`` or ``NAME.log.gz``
    (any other suffix: the name without its last suffixes ``.gz`` and ``.log``)."""
    p = Path(log)
    name = p.name
    for suffix in (".gz", ".log"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
    return p.with_name(name + ".truth.tsv")


def read_truth_tsv(path: str | os.PathLike[str]) -> list[tuple[float, Pose]]:
    """The rows ``timestamp x y theta`` of a truth file (one per laser line of the log, in
    order; ``#`` lines and blank lines skipped).

    Raises
    ------
    CarmenError
        When the file cannot be read or a row is not four finite numbers.
    """
    where = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise CarmenError(f"{where}: no such file") from None
    except OSError as exc:
        raise CarmenError(f"{where}: {exc.strerror or exc}") from None
    rows: list[tuple[float, Pose]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        try:
            vals = [float(f) for f in fields]
        except ValueError:
            raise CarmenError(f"{where}:{number}: truth row is not numbers: {line.strip()[:60]!r}") from None
        if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
            raise CarmenError(f"{where}:{number}: truth row must be 4 finite numbers (t x y theta)")
        rows.append((vals[0], Pose(vals[1], vals[2], vals[3])))
    return rows


# ---------------------------------------------------------------------------- writing
def write_carmen(
    path: str | os.PathLike[str],
    scans: Iterable[LaserScan],
    *,
    fov: float,
    max_range: float,
    comment: str | None = None,
    time_increment: float = 0.0,
) -> int:
    """Write scans as a CARMEN log, atomically: ``PARAM`` lines for the field of view
    (``laser_front_laser_fov``, degrees) and the maximum range (``robot_front_laser_max``),
    then one ``FLASER`` line per scan with its ``odom`` in both pose slots (the simulator's
    laser sits at the robot's centre), hostname ``wiremap`` and ``t`` as both timestamps.

    Ranges are written with 4 decimals (0.1 mm), poses with 6; no return (``inf``, ``nan``,
    ``>= max_range``) is written as ``max_range``, and a return that would print as
    ``max_range`` is written just below it, so that reading gives back the same returns. A
    ``path`` ending in ``.gz`` is written gzip-compressed (as the reader takes it).

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
    time_increment : float
        Seconds from one beam to the next, written as ``wiremap_front_laser_time_increment``
        when not 0 (a spinning lidar's scans; the timestamps are the first beams').

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
    if time_increment:
        if not math.isfinite(time_increment):
            raise ValueError(f"time_increment must be a finite number of seconds, got {time_increment}")
        out.write(f"PARAM {TIME_INCREMENT_PARAMS[0]} {time_increment:.9g}\n")
    below = max_range - 1e-4  # the largest value that prints below max_range at 4 decimals
    count = 0
    for k, s in enumerate(scans):
        n = s.ranges.size
        if not np.allclose(s.angles, flaser_angles(n, fov), atol=1e-9):
            raise ValueError(f"scan {k}: its {n} bearings are not the FLASER bearings of a "
                             f"{fov:g} rad field of view")
        r = np.asarray(s.ranges, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            miss = ~np.isfinite(r) | (r >= max_range) | ~(r > 0.0)
        r = np.where(miss, max_range, np.minimum(r, below))
        text = " ".join(f"{v:.4f}" for v in r.tolist())
        o = s.odom
        pose = f"{o.x:.6f} {o.y:.6f} {o.theta:.6f}"
        out.write(f"FLASER {n} {text} {pose} {pose} {s.t:.6f} {HOSTNAME} {s.t:.6f}\n")
        count += 1
    text = out.getvalue()
    write_atomic(path, gzip.compress(text.encode(), compresslevel=6, mtime=0) if str(path).endswith(".gz")
                 else text)
    return count


# ---------------------------------------------------------------------------- truth per scan
def scan_truth(log: CarmenLog, truth_file: str | os.PathLike[str] | None = None) -> list[Pose] | None:
    """The true pose of the **laser** at each scan of ``log``, or None when the log has none.

    The truth is, in this order: ``truth_file`` when given; else ``NAME.truth.tsv`` beside the
    log (:func:`truth_path_for`) when it exists -- one row per line of the log's laser stream,
    matched by :attr:`LaserScan.index` (so skipped lines keep the rows aligned) and describing
    what the line's odometry slot describes (each row is composed with the scan's ``mount``);
    else the ``TRUEPOS`` track (the robot's true pose), interpolated linearly at each scan's
    time and composed with the scan's ``mount``.

    Raises
    ------
    CarmenError
        When the truth file cannot be read or has fewer rows than the log has laser lines.
    """
    path = Path(truth_file) if truth_file is not None else truth_path_for(log.path)
    if truth_file is not None or path.is_file():
        rows = read_truth_tsv(path)
        lines = log.lasers.get(log.laser or "", 0)
        if len(rows) < lines:
            raise CarmenError(f"{path}: {len(rows)} truth rows, but {log.path} has {lines} {log.laser} lines")
        return [rows[s.index][1].compose(s.mount) for s in log.scans]
    if not log.truepos:
        return None
    t = np.array([tp[0] for tp in log.truepos])
    order = np.argsort(t, kind="stable")
    t = t[order]
    xyt = np.array([[p.x, p.y, p.theta] for _, p in log.truepos])[order]
    th = np.unwrap(xyt[:, 2])
    out = []
    for s in log.scans:
        pose = Pose(float(np.interp(s.t, t, xyt[:, 0])), float(np.interp(s.t, t, xyt[:, 1])),
                    float(np.interp(s.t, t, th)))
        out.append(pose.compose(s.mount))
    return out
