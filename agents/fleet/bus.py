"""The fleet bus: Zenoh key expressions, session configuration and shutdown handling.

Every process of a fleet (router, robot agents, fusion service, ``wiremap run``) opens its
Zenoh session through :func:`open_session`, with the flags of :func:`add_bus_arguments`. Key
expressions (documented in ``ARCHITECTURE.md``)::

    wiremap/<fleet>/robots/<id>/map    a robot's best wireframe (wire_codec bytes)
    wiremap/<fleet>/robots/<id>/pose   pose + status at 10 Hz (msgpack, see encode_pose)
    wiremap/<fleet>/robots/<id>/viz    scan + particles for the recorder (msgpack, a few Hz)
    wiremap/<fleet>/alive/<id>         liveliness token of a robot process
    wiremap/<fleet>/fused/map          the fused map (wire_codec bytes); also a queryable
    wiremap/<fleet>/fused/stats        the fusion service's counters (JSON), a queryable only

Waiting for the router: a Zenoh client with ``connect/timeout_ms: -1`` blocks inside Rust and
cannot be interrupted by SIGTERM, so :func:`open_session` instead retries a fail-fast
``zenoh.open`` from Python every few hundred milliseconds until it connects or the stop flag
is set. After the first connection Zenoh reconnects by itself when the router restarts.

Credentials (``--credentials FILE``, :mod:`agents.fleet.secure`): a refused login (wrong password, no
or a foreign certificate, ``tcp/`` to a ``tls/`` router) fails ``zenoh.open`` with the same
"Unable to connect" as an absent router. :func:`open_session` tells them apart by trying a plain
TCP connection to the endpoint: when something listens there twice in a row while Zenoh cannot
connect, the router is there and refused us, and waiting would be forever.
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import socket
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

import msgpack
import numpy as np

from agents.errors import UserError
from mapping.se2 import Pose
from mapping.wireframe import Wireframe

if TYPE_CHECKING:  # zenoh is imported lazily: `wiremap worlds` must not pay for it
    import zenoh

DEFAULT_PORT = 7447
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
DEFAULT_FLEET = "default"
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$")  # the one rule for robot ids and fleet names

# The embedded default router: loopback only, multicast scouting off. broker_config/router.json5
# is the same configuration as a file (a test checks that they agree).
ROUTER_DEFAULTS: dict[str, Any] = {
    "mode": "router",
    "listen/endpoints": [DEFAULT_ENDPOINT],
    "scouting/multicast/enabled": False,
}
CLIENT_DEFAULTS: dict[str, Any] = {
    "mode": "client",
    "connect/endpoints": [DEFAULT_ENDPOINT],
    "scouting/multicast/enabled": False,
}


def valid_name(name: object) -> bool:
    """Whether ``name`` is usable as one key-expression chunk (a robot id, a fleet name; see
    :func:`check_name`)."""
    return isinstance(name, str) and _NAME_RE.match(name) is not None


def check_name(name: str, what: str = "robot id") -> str:
    """Return ``name`` if it is usable as one key-expression chunk, else raise ``UserError``.

    Allowed: 1-63 characters of letters, digits, ``_``, ``.``, ``-``, starting with a letter or
    digit (no ``/``, ``*``, ``$``, ``?``, ``#`` or spaces, which Zenoh treats specially).
    """
    if not valid_name(name):
        raise UserError(f"bad {what} {name!r}: use 1-63 letters, digits, '_', '.', '-'")
    return name


@dataclass(frozen=True)
class FleetKeys:
    """The key expressions of one fleet (``wiremap/<fleet>/...``)."""

    fleet: str = DEFAULT_FLEET

    def __post_init__(self) -> None:
        check_name(self.fleet, "fleet name")

    @property
    def prefix(self) -> str:
        return f"wiremap/{self.fleet}"

    def robot_map(self, robot: str) -> str:
        return f"{self.prefix}/robots/{check_name(robot)}/map"

    def robot_pose(self, robot: str) -> str:
        return f"{self.prefix}/robots/{check_name(robot)}/pose"

    def robot_viz(self, robot: str) -> str:
        return f"{self.prefix}/robots/{check_name(robot)}/viz"

    def alive(self, robot: str) -> str:
        return f"{self.prefix}/alive/{check_name(robot)}"

    @property
    def fused_map(self) -> str:
        return f"{self.prefix}/fused/map"

    @property
    def fusion_stats(self) -> str:
        """The fusion service's counters (JSON), answered by a queryable. Under ``fused/`` so
        that the fleet ACL (:func:`agents.fleet.secure.acl_config`) lets the fusion identity answer
        and any authenticated client ask."""
        return f"{self.prefix}/fused/stats"

    @property
    def admin_forget(self) -> str:
        """``wiremap fleet forget ID``: a query (payload ``forget=ID``) the fusion service
        answers; in a secure fleet only the admin identity may ask
        (:func:`agents.fleet.secure.acl_config`)."""
        return f"{self.prefix}/admin/forget"

    @property
    def all_maps(self) -> str:
        return f"{self.prefix}/robots/*/map"

    @property
    def all_poses(self) -> str:
        return f"{self.prefix}/robots/*/pose"

    @property
    def all_viz(self) -> str:
        return f"{self.prefix}/robots/*/viz"

    @property
    def all_alive(self) -> str:
        return f"{self.prefix}/alive/*"

    def robot_of(self, key: str) -> str | None:
        """The robot id in a concrete key of this fleet (``.../robots/<id>/...`` or
        ``.../alive/<id>``), or None for any other key."""
        parts = str(key).split("/")
        head = self.prefix.split("/")
        if parts[:2] != head:
            return None
        rest = parts[2:]
        if len(rest) == 3 and rest[0] == "robots":
            rid = rest[1]
        elif len(rest) == 2 and rest[0] == "alive":
            rid = rest[1]
        else:
            return None
        return rid if valid_name(rid) else None


# ---------------------------------------------------------------------- command-line flags
def add_bus_arguments(parser: argparse.ArgumentParser, *, router: bool = False) -> None:
    """The bus flags every fleet process takes: ``--connect``, ``--config``, ``--credentials``,
    ``--fleet`` and, for routers, ``--listen``. Flags given on the command line override the
    config file; the credentials file (:mod:`agents.fleet.secure`) is applied last."""
    g = parser.add_argument_group("bus (Zenoh)")
    g.add_argument(
        "--connect",
        metavar="ENDPOINT",
        action="append",
        default=[],
        help=f"Zenoh endpoint to connect to, repeatable (default {DEFAULT_ENDPOINT}"
        + (" for clients; none for a router)" if router else ")"),
    )
    g.add_argument("--config", metavar="FILE", help="Zenoh JSON5 configuration file (see broker_config/)")
    g.add_argument(
        "--credentials",
        metavar="FILE",
        help="credentials file (user/password and/or TLS certificates; see broker_config/secure/)",
    )
    g.add_argument(
        "--fleet", default=DEFAULT_FLEET, help=f"fleet name, the second key chunk (default {DEFAULT_FLEET})"
    )
    g.add_argument("--parent-pid", type=int, default=None, help=argparse.SUPPRESS)
    if router:
        g.add_argument(
            "--listen",
            metavar="ENDPOINT",
            action="append",
            default=[],
            help=f"endpoint to listen on, repeatable (default {DEFAULT_ENDPOINT})",
        )


def fleet_keys(args: argparse.Namespace) -> FleetKeys:
    return FleetKeys(check_name(getattr(args, "fleet", DEFAULT_FLEET) or DEFAULT_FLEET, "fleet name"))


def one_line(exc: BaseException | str) -> str:
    """An error text on one line, without Zenoh's ``at <file>.rs:<line>`` source locations."""
    text = re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(exc))
    text = " ".join(text.split())
    return text[:300] + ("..." if len(text) > 300 else "")


def _insert(cfg: zenoh.Config, key: str, value: Any) -> None:
    cfg.insert_json5(key, json.dumps(value))


def _get(cfg: zenoh.Config, key: str) -> Any:
    try:
        return json.loads(cfg.get_json(key))
    except Exception:
        return None


def build_config(
    mode: str,
    config_file: str | None = None,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
) -> zenoh.Config:
    """A Zenoh configuration for a fleet process.

    Parameters
    ----------
    mode : ``"client"``, ``"peer"`` or ``"router"``; used when the file sets no mode.
    config_file : a JSON5 file (``broker_config/*.json5``); without one, the embedded defaults
        (:data:`ROUTER_DEFAULTS` / :data:`CLIENT_DEFAULTS`: loopback, multicast scouting off).
    connect, listen : endpoints that replace the file's ``connect/endpoints`` /
        ``listen/endpoints``.

    Raises
    ------
    UserError
        When the file cannot be read or an endpoint is rejected.
    """
    import zenoh

    if config_file:
        if not Path(config_file).is_file():
            raise UserError(f"{config_file}: no such file")
        try:
            cfg = zenoh.Config.from_file(config_file)
        except Exception as exc:
            raise UserError(f"{config_file}: not a valid Zenoh configuration: {one_line(exc)}") from None
        if _get(cfg, "mode") is None:
            _insert(cfg, "mode", mode)
    else:
        cfg = zenoh.Config()
        for k, v in (ROUTER_DEFAULTS if mode == "router" else CLIENT_DEFAULTS).items():
            _insert(cfg, k, v)
        _insert(cfg, "mode", mode)
        if mode != "router":
            cfg.insert_json5("listen/endpoints", "[]")
    try:
        if connect:
            _insert(cfg, "connect/endpoints", list(connect))
        if listen:
            _insert(cfg, "listen/endpoints", list(listen))
    except Exception as exc:
        raise UserError(f"bad endpoint in {list(connect) + list(listen)}: {one_line(exc)}") from None
    return cfg


def config_from_args(args: argparse.Namespace, mode: str = "client") -> zenoh.Config:
    """:func:`build_config` from the flags of :func:`add_bus_arguments`, then the
    ``--credentials`` file applied (:func:`agents.fleet.secure.apply_credentials`).

    Raises
    ------
    UserError
        A bad config file or endpoint, a missing or bad credentials file.
    """
    cfg = build_config(
        mode,
        getattr(args, "config", None),
        getattr(args, "connect", None) or (),
        getattr(args, "listen", None) or (),
    )
    cred_file = getattr(args, "credentials", None)
    if cred_file:
        from agents.fleet.secure import apply_credentials, load_credentials

        apply_credentials(cfg, load_credentials(cred_file))
    return cfg


def connect_endpoints(cfg: zenoh.Config) -> list[str]:
    """The ``connect/endpoints`` of a configuration as a flat list (a per-mode map is flattened)."""
    v = _get(cfg, "connect/endpoints")
    if isinstance(v, dict):
        return [str(e) for eps in v.values() if isinstance(eps, list) for e in eps]
    if isinstance(v, list):
        return [str(e) for e in v]
    return []


def refused_endpoint(cfg: zenoh.Config) -> str | None:
    """A connect endpoint of ``cfg`` where something accepts TCP connections, or None.

    Called after ``zenoh.open`` failed with "Unable to connect": a listening endpoint means the
    router is there and refused the login (see the module docstring)."""
    from agents.fleet.secure import endpoint_reachable

    for ep in connect_endpoints(cfg):
        if endpoint_reachable(ep, timeout=0.5):
            return ep
    return None


#: Seconds between two "waiting for a router" reports of :func:`open_session`.
WAIT_REPORT_S = 10.0


def open_session(
    cfg: zenoh.Config,
    stop: threading.Event | StopFlag | None = None,
    wait: bool = True,
    timeout: float | None = None,
    on_wait: Any = None,
) -> zenoh.Session | None:
    """Open a Zenoh session, waiting for the router if it is not up yet.

    Parameters
    ----------
    cfg : from :func:`build_config`.
    stop : when set while waiting, give up and return None (SIGTERM during the wait).
    wait : False: fail at once when no router answers.
    timeout : give up after this many seconds (None: wait until ``stop``).
    on_wait : called with the error text (which names the endpoints tried) when the first
        attempt fails and every 10 s after that, with the seconds waited (to print "waiting for
        a router ...").

    Raises
    ------
    UserError
        When the session cannot be opened for another reason than an absent router (a port in
        use, a bad certificate), or ``wait`` is False, or ``timeout`` passes, or the router is
        listening but refused us twice in a row (``router at EP refused us: ...``; a wrong
        password or certificate, or ``tcp/`` vs ``tls/``).
    """
    import zenoh

    t0 = time.monotonic()
    delay = 0.05
    told = False
    told_at = 0.0
    refusals = 0
    while True:
        try:
            return zenoh.open(cfg)
        except zenoh.ZError as exc:
            text = one_line(exc)
            if "Unable to connect" in text:
                ep = refused_endpoint(cfg)
                refusals = refusals + 1 if ep is not None else 0
                # twice in a row: a router that was just starting up is not mistaken for a refusal
                if ep is not None and (refusals >= 2 or not wait):
                    raise UserError(
                        f"router at {ep} refused us: check --credentials and tls/ vs tcp/"
                    ) from None
            if not wait or "Unable to connect" not in text:
                raise UserError(f"cannot open Zenoh session: {text}") from None
            if timeout is not None and time.monotonic() - t0 > timeout:
                raise UserError(f"no router after {timeout:g} s: {text}") from None
            waited = time.monotonic() - t0
            if on_wait is not None and (not told or waited - told_at >= WAIT_REPORT_S):
                on_wait(text if not told else f"{waited:.0f} s so far: {text}")
                told, told_at = True, waited
        if stop is not None:
            if stop.wait(delay):
                return None
        else:
            time.sleep(delay)
        delay = min(delay * 1.5, 0.5)


# ---------------------------------------------------------------------- shutdown
class StopFlag:
    """A ``threading.Event`` set by SIGTERM/SIGINT (and by :meth:`set`).

    Use as a context manager in the main thread: it installs the handlers on entry and restores
    the previous ones on exit. The main loop polls :meth:`wait`, leaves its ``with
    zenoh.open(...)`` block and so closes every subscriber and queryable (a callback subscriber
    left open makes the process hang at exit).
    """

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: int | None = None
        self._old: dict[int, Any] = {}

    def _handler(self, signum: int, _frame: FrameType | None) -> None:
        self.signal = signum
        self.event.set()

    def __enter__(self) -> StopFlag:
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGTERM, signal.SIGINT):
                self._old[s] = signal.signal(s, self._handler)
        return self

    def __exit__(self, *_exc: object) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old.clear()

    def set(self) -> None:
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        return self.event.wait(timeout)


def watch_parent(pid: int | None, stop: StopFlag | threading.Event, period: float = 0.5) -> None:
    """Set ``stop`` when the process ``pid`` (our parent, e.g. ``wiremap run``) is gone, so that
    a killed parent does not leave its fleet running (a daemon thread polls ``os.getppid``)."""
    import os

    if not pid:
        return

    def loop() -> None:
        while not stop.wait(period):
            if os.getppid() != pid:
                stop.set()
                return

    threading.Thread(target=loop, name="watch-parent", daemon=True).start()


# ---------------------------------------------------------------------- small payloads
def encode_pose(
    *,
    seq: int,
    t: float,
    stamp_ns: int,
    odom: Pose,
    fleet: Pose,
    truth: Pose | None = None,
    status: dict[str, Any] | None = None,
) -> bytes:
    """The pose message (msgpack map): ``seq``, ``t`` (sim seconds), ``stamp_ns`` (wall clock),
    ``odom`` / ``fleet`` / ``truth`` as ``[x, y, theta]`` (truth: None unless simulated) and a
    ``status`` map (``step``, ``vertices``, ``edges``, ``maps_sent``, ``bytes_sent``, ...)."""
    return bytes(
        msgpack.packb(
            {
                "seq": int(seq),
                "t": float(t),
                "stamp_ns": int(stamp_ns),
                "odom": list(odom.as_tuple()),
                "fleet": list(fleet.as_tuple()),
                "truth": None if truth is None else list(truth.as_tuple()),
                "status": dict(status or {}),
            },
            use_bin_type=True,
        )
    )


def decode_pose(data: bytes) -> dict[str, Any]:
    """Inverse of :func:`encode_pose`; poses come back as :class:`Pose`, every field checked by
    :func:`agents.fleet.validate.pose`. Raises ``ValueError`` (:class:`~agents.fleet.validate.Invalid`,
    with a ``reason``)."""
    from agents.fleet import validate

    return validate.pose(data)


def pack_wireframe(wf: Wireframe) -> dict[str, Any]:
    """A lossy (float32) msgpack-able form of a wireframe, for visualisation payloads only."""
    return {
        "p": np.asarray(wf.points, dtype="<f4").tobytes(),
        "l": np.asarray(wf.labels, dtype=np.uint8).tobytes(),
        "e": np.asarray(wf.edges, dtype="<i4").tobytes(),
    }


def unpack_wireframe(d: dict[str, Any]) -> Wireframe:
    pts = np.frombuffer(d["p"], dtype="<f4").astype(np.float64).reshape(-1, 2)
    labels = np.frombuffer(d["l"], dtype=np.uint8)
    edges = np.frombuffer(d["e"], dtype="<i4").reshape(-1, 2)
    return Wireframe.build(pts, edges, labels)


def encode_viz(
    *, t: float, scan: Wireframe, pose: Pose, particles: Sequence[Wireframe], weights: Sequence[float]
) -> bytes:
    """The visualisation message: ``t``, the current ``scan`` (robot frame), the estimated
    ``pose`` (odometry frame) at the scan, every particle's wireframe and weight."""
    return bytes(
        msgpack.packb(
            {
                "t": float(t),
                "pose": list(pose.as_tuple()),
                "scan": pack_wireframe(scan),
                "particles": [pack_wireframe(w) for w in particles],
                "weights": [float(w) for w in weights],
            },
            use_bin_type=True,
        )
    )


def decode_viz(data: bytes) -> dict[str, Any]:
    """Inverse of :func:`encode_viz`, every field checked by :func:`agents.fleet.validate.viz`.
    Raises ``ValueError`` (:class:`~agents.fleet.validate.Invalid`, with a ``reason``)."""
    from agents.fleet import validate

    return validate.viz(data)


# ---------------------------------------------------------------------- ports
def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bind port 0)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def tcp_endpoint(port: int, host: str = "127.0.0.1") -> str:
    return f"tcp/{host}:{int(port)}"


@contextmanager
def session_scope(cfg: zenoh.Config, stop: threading.Event | None = None) -> Iterator[zenoh.Session | None]:
    """``with session_scope(cfg, stop) as s:`` opens (waiting for the router) and always closes."""
    s = open_session(cfg, stop)
    try:
        yield s
    finally:
        if s is not None:
            s.close()
