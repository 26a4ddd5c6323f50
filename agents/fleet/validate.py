"""The one place where what arrives on the bus is checked before anything uses it.

Every message type of the fleet has one function here that takes the payload (bytes, or a
decoded :class:`~wire_codec.message.MapMessage`) and returns values every consumer can use
without further checks, or raises :class:`Invalid` with a short ``reason`` (the counter a
consumer files the drop under, e.g. ``fused/stats``' ``side_dropped_by``) and a detail:

* :func:`pose` -- ``robots/<id>/pose`` (seq, t, stamp_ns, odom/fleet/truth poses, status);
* :func:`status` -- the status map inside a pose (also alone, from a status file);
* :func:`viz` -- ``robots/<id>/viz`` (t, pose, scan, particles, weights);
* :func:`robot_map` -- the content of a decoded ``robots/<id>/map`` (resolution, extent, meta);
* :func:`fused_map` -- ``fused/map`` as ``watch`` and ``run`` read it;
* :func:`stats_doc` -- ``fused/stats`` as a client reads it;
* :func:`admin_request` -- the payload of a ``fused/admin`` query.

The rules: numbers are finite and in range (times within :data:`MAX_SIM_T`, wall clocks within
:data:`MAX_NS`, coordinates within :data:`MAX_COORD`, counts non-negative and below
:data:`MAX_COUNT`), of the right type (``bool`` is not an integer), strings short, lists and
maps bounded. Unknown status keys are dropped, not passed on. Each function documents what it
raises; nothing else escapes (a property test, ``tests/test_validate.py``, drives every
function and every consumer with hostile values).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import msgpack
import numpy as np

from mapping.se2 import Pose
from mapping.wireframe import Wireframe

MAX_SIM_T = 1.0e10  # simulated or log seconds: a log stamped in Unix time (belgioioso: 1.02e9) fits, to 2286
MAX_NS = (1 << 63) - 1  # a wall clock in ns, a sequence number
MAX_COUNT = 1 << 53  # counters in a status (exact in a float)
MAX_COORD = 1.0e5  # metres in any frame of a pose (a building is a few hundred)
MAX_THETA = 1.0e3  # radians before wrapping (anything finite wraps; this bounds the work)
MAX_STRING = 256
MAX_STATUS_KEYS = 64
MAX_PARTICLES = 4096
MAX_VIZ_VERTICES = 100_000  # over all wireframes of one viz message

# status fields a robot sends (agents.fleet.robot.RobotStatus) and their kinds
STATUS_INTS = ("step", "vertices", "edges", "maps_sent", "bytes_sent", "pose_bytes", "viz_bytes")
STATUS_FLOATS = ("t", "step_ms")
STATUS_BOOLS = ("finished",)


class Invalid(ValueError):
    """A payload that failed a check: ``reason`` (a short counter name) and the detail."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


def _short(v: object) -> str:
    try:
        text = repr(v)
    except Exception:  # a repr that raises is hostile too
        text = f"<{type(v).__name__}>"
    return text[:60] + ("..." if len(text) > 60 else "")


# ---------------------------------------------------------------------- scalars
def integer(v: object, what: str, lo: int = 0, hi: int = MAX_NS, reason: str = "range") -> int:
    """``v`` as an ``int`` in ``[lo, hi]`` (``bool`` and floats are refused)."""
    if isinstance(v, bool) or not isinstance(v, int):
        raise Invalid("type", f"{what} {_short(v)} is not an integer")
    if not lo <= v <= hi:
        raise Invalid(reason, f"{what} {_short(v)} is outside [{lo}, {hi}]")
    return int(v)


def number(v: object, what: str, lo: float, hi: float, reason: str = "range") -> float:
    """``v`` as a finite ``float`` in ``[lo, hi]`` (ints accepted, ``bool`` refused)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise Invalid("type", f"{what} {_short(v)} is not a number")
    try:
        f = float(v)
    except OverflowError:
        raise Invalid(reason, f"{what} is too large") from None
    if not math.isfinite(f):
        raise Invalid("not_finite", f"{what} {_short(v)} is not finite")
    if not lo <= f <= hi:
        raise Invalid(reason, f"{what} {f:g} is outside [{lo:g}, {hi:g}]")
    return f


def sim_time(v: object, what: str = "t") -> float:
    """A simulated / log time in seconds: finite, in ``[0, MAX_SIM_T]``."""
    return number(v, what, 0.0, MAX_SIM_T, reason="time")


def pose_value(v: object, what: str) -> Pose:
    """``[x, y, theta]`` (3 finite numbers, ``|x|, |y| <= MAX_COORD``) as a :class:`Pose`."""
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise Invalid("type", f"{what} {_short(v)} is not [x, y, theta]")
    x = number(v[0], f"{what}.x", -MAX_COORD, MAX_COORD, reason="extent")
    y = number(v[1], f"{what}.y", -MAX_COORD, MAX_COORD, reason="extent")
    th = number(v[2], f"{what}.theta", -MAX_THETA, MAX_THETA)
    return Pose(x, y, th)


def _unpack(data: object, what: str, max_bytes: int, **limits: int) -> Any:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise Invalid("type", f"{what} payload is a {type(data).__name__}, not bytes")
    if len(data) > max_bytes:
        raise Invalid("oversized", f"{what} payload of {len(data)} bytes (limit {max_bytes})")
    try:
        return msgpack.unpackb(
            bytes(data), raw=False, strict_map_key=True, max_map_len=1024, max_array_len=1 << 16, **limits
        )
    except Exception as exc:  # msgpack raises many classes (ValueError, TypeError, its own)
        raise Invalid("undecodable", f"{what} is not msgpack: {type(exc).__name__}") from None


def _mapping(v: object, what: str) -> Mapping[str, Any]:
    if not isinstance(v, dict):
        raise Invalid("type", f"{what} is a {type(v).__name__}, not a map")
    return v


# ---------------------------------------------------------------------- pose and status
def status(v: object) -> dict[str, Any]:
    """A robot's status map with the known fields checked (:data:`STATUS_INTS`,
    :data:`STATUS_FLOATS`, :data:`STATUS_BOOLS`); unknown keys are dropped, missing ones left
    out. ``None`` is an empty status. Raises :class:`Invalid`."""
    if v is None:
        return {}
    d = _mapping(v, "status")
    if len(d) > MAX_STATUS_KEYS:
        raise Invalid("oversized", f"status has {len(d)} keys (limit {MAX_STATUS_KEYS})")
    out: dict[str, Any] = {}
    for k in STATUS_INTS:
        if k in d:
            out[k] = integer(d[k], f"status.{k}", 0, MAX_COUNT)
    for k in STATUS_FLOATS:
        if k in d:
            out[k] = sim_time(d[k], f"status.{k}")
    for k in STATUS_BOOLS:
        if k in d:
            if not isinstance(d[k], bool):
                raise Invalid("type", f"status.{k} {_short(d[k])} is not a boolean")
            out[k] = d[k]
    return out


def pose(data: object, max_bytes: int = 16 * 1024) -> dict[str, Any]:
    """A pose message (:func:`agents.fleet.bus.encode_pose`): ``{seq, t, stamp_ns, odom, fleet,
    truth, status}`` with poses as :class:`Pose` (``truth`` may be None) and the status from
    :func:`status`. Raises :class:`Invalid`."""
    d = _mapping(_unpack(data, "pose", max_bytes, max_bin_len=1 << 12, max_str_len=1 << 12), "pose")
    for k in ("seq", "t", "stamp_ns", "odom", "fleet"):
        if k not in d:
            raise Invalid("missing", f"pose has no {k!r}")
    truth = d.get("truth")
    return {
        "seq": integer(d["seq"], "seq"),
        "t": sim_time(d["t"]),
        "stamp_ns": integer(d["stamp_ns"], "stamp_ns"),
        "odom": pose_value(d["odom"], "odom"),
        "fleet": pose_value(d["fleet"], "fleet"),
        "truth": None if truth is None else pose_value(truth, "truth"),
        "status": status(d.get("status")),
    }


# ---------------------------------------------------------------------- visualisation
def _wireframe(v: object, what: str, budget: list[int]) -> Wireframe:
    d = _mapping(v, what)
    try:
        p, lab, e = d["p"], d["l"], d["e"]
    except KeyError:
        raise Invalid("missing", f"{what} lacks p, l or e") from None
    if not all(isinstance(b, bytes) for b in (p, lab, e)):
        raise Invalid("type", f"{what} arrays are not bytes")
    if len(p) % 8 or len(e) % 8 or len(lab) * 8 != len(p):
        raise Invalid("shape", f"{what} array sizes do not agree")
    n = len(lab)
    budget[0] -= n
    if budget[0] < 0:
        raise Invalid("oversized", f"more than {MAX_VIZ_VERTICES} vertices in one viz message")
    pts = np.frombuffer(p, dtype="<f4").astype(np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(pts)) or (n and float(np.abs(pts).max()) > MAX_COORD):
        raise Invalid("extent", f"{what} has a non-finite or far vertex")
    try:
        return Wireframe.build(pts, np.frombuffer(e, dtype="<i4").reshape(-1, 2),
                               np.frombuffer(lab, dtype=np.uint8))
    except ValueError as exc:
        raise Invalid("shape", f"{what}: {exc}") from None


def viz(data: object, max_bytes: int = 4 * 1024 * 1024) -> dict[str, Any]:
    """A visualisation message (:func:`agents.fleet.bus.encode_viz`): ``{t, pose, scan,
    particles, weights}``; weights finite, non-negative, one per particle. Raises
    :class:`Invalid`."""
    d = _mapping(_unpack(data, "viz", max_bytes, max_bin_len=max_bytes, max_str_len=1 << 12), "viz")
    for k in ("t", "pose", "scan", "particles", "weights"):
        if k not in d:
            raise Invalid("missing", f"viz has no {k!r}")
    parts, weights = d["particles"], d["weights"]
    if not isinstance(parts, list) or not isinstance(weights, list):
        raise Invalid("type", "particles and weights must be lists")
    if len(parts) > MAX_PARTICLES or len(weights) != len(parts):
        raise Invalid("shape", f"{len(parts)} particles, {len(weights)} weights (limit {MAX_PARTICLES})")
    budget = [MAX_VIZ_VERTICES]
    return {
        "t": sim_time(d["t"]),
        "pose": pose_value(d["pose"], "pose"),
        "scan": _wireframe(d["scan"], "scan", budget),
        "particles": [_wireframe(w, f"particle {i}", budget) for i, w in enumerate(parts)],
        "weights": [number(w, "weight", 0.0, 1.0e300) for w in weights],
    }


# ---------------------------------------------------------------------- maps
def map_meta(meta: object, *, fused: bool = False) -> dict[str, Any]:
    """The ``meta`` of a map message, checked: robot maps' ``boot`` (int ns), ``t``
    (:func:`sim_time`), ``step`` (count); fused maps' ``version`` (int), ``threshold`` (positive
    metres), ``stale`` (list of robot ids), ``t``. Absent fields are left out; unknown ones are
    kept only when they are short scalars. Raises :class:`Invalid` (reason ``meta``)."""
    from agents.fleet.bus import valid_name

    if not isinstance(meta, dict):
        raise Invalid("meta", f"meta is a {type(meta).__name__}, not a map")
    try:
        out: dict[str, Any] = {}
        if "t" in meta:
            out["t"] = sim_time(meta["t"], "meta.t")
        if fused:
            if "version" in meta:
                out["version"] = integer(meta["version"], "meta.version")
            if "threshold" in meta:
                out["threshold"] = number(meta["threshold"], "meta.threshold", 1e-6, 100.0)
            if "stale" in meta:
                st = meta["stale"]
                if not isinstance(st, list) or len(st) > 256 or not all(valid_name(r) for r in st):
                    raise Invalid("meta", "meta.stale is not a list of robot ids")
                out["stale"] = list(st)
        else:
            if "boot" in meta:
                out["boot"] = integer(meta["boot"], "meta.boot")
            if "step" in meta:
                out["step"] = integer(meta["step"], "meta.step", 0, MAX_COUNT)
        for k, v in meta.items():
            if k in out or not isinstance(k, str) or len(k) > 64:
                continue
            if isinstance(v, bool) or (isinstance(v, int) and abs(v) <= MAX_NS):
                out[k] = v
            elif isinstance(v, float) and math.isfinite(v):
                out[k] = v
            elif isinstance(v, str) and len(v) <= MAX_STRING:
                out[k] = v
    except Invalid as exc:
        raise Invalid("meta", exc.detail) from None
    return out


def robot_map(
    msg: Any, max_extent_m: float, max_resolution_m: float,
    fleet_points: Callable[[], np.ndarray] | None = None,
) -> tuple[str, str] | None:
    """``(reason, detail)`` when a decoded robot map's content is absurd, else None.

    Reasons: ``resolution`` (not in ``(0, max_resolution_m]``), ``extent`` (origin or a vertex
    beyond ``max_extent_m`` in the fleet frame), ``meta`` (:func:`map_meta`: ``boot`` not a
    non-negative int, ``t`` not a time in ``[0, MAX_SIM_T]``, ``step`` not a count), ``seq`` (not
    in ``[0, 2^63)``), ``stamp`` (``stamp_ns`` not in ``[0, 2^63)``). Never raises.
    ``fleet_points``: gives ``msg.origin.apply(msg.wireframe.points)`` when the caller keeps it
    (the fusion's intake, :mod:`agents.fleet.fusion.facts`)."""
    try:
        res = float(msg.resolution)
        if not (0.0 < res <= max_resolution_m):
            return "resolution", f"resolution {res:g} m (limit {max_resolution_m:g} m)"
        o = msg.origin
        if not (math.isfinite(o.x) and math.isfinite(o.y)) or max(abs(o.x), abs(o.y)) > max_extent_m:
            return "extent", f"origin ({o.x:.1f}, {o.y:.1f}) is over {max_extent_m:g} m away"
        wf = msg.wireframe
        if wf.n_vertices:
            far = float(np.abs(o.apply(wf.points) if fleet_points is None else fleet_points()).max())
            if not math.isfinite(far) or far > max_extent_m:
                return "extent", f"a vertex is {far:.1f} m from the fleet origin (limit {max_extent_m:g} m)"
        try:
            integer(msg.seq, "seq")
        except Invalid as exc:
            return "seq", exc.detail
        try:
            integer(msg.stamp_ns, "stamp_ns")
        except Invalid as exc:
            return "stamp", exc.detail
        try:
            map_meta(msg.meta)
        except Invalid as exc:
            return "meta", exc.detail
    except Exception as exc:  # a message object that is not what the codec makes
        return "type", f"{type(exc).__name__}: {str(exc)[:120]}"
    return None


def fused_map(data: object) -> Any:
    """A ``fused/map`` payload as ``watch`` and ``run`` read it: a decodable ``FUSED_MAP`` whose
    ``meta`` passes :func:`map_meta` (``fused=True``; the message's meta is replaced by the
    checked one) and whose robot list holds valid ids. Raises :class:`Invalid`."""
    import dataclasses

    from agents.fleet.bus import valid_name
    from wire_codec import decode
    from wire_codec.message import MessageKind

    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise Invalid("type", f"fused map payload is a {type(data).__name__}")
    try:
        msg = decode(bytes(data))
    except ValueError as exc:
        raise Invalid("malformed", str(exc)[:200]) from None
    if msg.kind != MessageKind.FUSED_MAP:
        raise Invalid("kind", f"{msg.kind.name.lower()} message from {msg.sender!r} on the fused key")
    if not all(valid_name(r) for r in msg.robots):
        raise Invalid("robots", "a contributor is not a robot id")
    for what, v in (("seq", msg.seq), ("stamp_ns", msg.stamp_ns)):
        integer(v, what)
    return dataclasses.replace(msg, meta=map_meta(msg.meta, fused=True))


def stats_doc(data: object) -> dict[str, Any]:
    """A ``fused/stats`` reply (JSON object, at most 1 MiB). Raises :class:`Invalid`.

    Only the shape is checked here; readers take fields with :func:`get_int`."""
    import json

    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) > 1 << 20:
        raise Invalid("type", "stats reply is not bytes of at most 1 MiB")
    try:
        doc = json.loads(bytes(data))
    except (ValueError, RecursionError):
        raise Invalid("undecodable", "stats reply is not JSON") from None
    return dict(_mapping(doc, "stats"))


def get_int(d: Mapping[str, Any], key: str, default: int = 0) -> int:
    """``d[key]`` when it is an int in ``[0, MAX_NS]``, else ``default`` (for display)."""
    v = d.get(key, default) if isinstance(d, Mapping) else default
    try:
        return integer(v, key)
    except Invalid:
        return default


def admin_request(params: object) -> tuple[str, str]:
    """An ``admin/forget`` query's payload (``forget=ID``) as ``("forget", id)``. Raises
    :class:`Invalid`."""
    from agents.fleet.bus import valid_name

    text = str(params) if params is not None else ""
    if len(text) > MAX_STRING:
        raise Invalid("oversized", "admin parameters too long")
    parts = dict(p.split("=", 1) for p in text.split(";") if "=" in p)
    rid = parts.get("forget")
    if rid is None or not valid_name(rid):
        raise Invalid("admin", f"unknown admin request {text[:60]!r} (expected forget=ID)")
    return "forget", rid
