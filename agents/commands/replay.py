"""``wiremap replay FILE.rrd [--web [--bind IP] [--port P]]``: open a Rerun recording.

Runs the ``rerun`` viewer that the rerun-sdk wheel installs (its native binary, see
:func:`find_rerun`; else ``<venv>/bin/rerun`` or the first ``rerun`` on ``PATH``) on the file,
forwards SIGINT/SIGTERM to it and returns its exit status (0 when stopped by a signal).

* On Linux without a display (neither ``DISPLAY`` nor ``WAYLAND_DISPLAY`` set) the native viewer
  cannot start: the command says so on one line, names the alternatives (``--web``, or
  ``rerun rrd stats FILE`` for a text summary) and exits 2 without starting anything.
* ``--web`` serves the recording with Rerun's web viewer instead (``rerun --serve-web``) on
  ``--bind`` (default 127.0.0.1, loopback only) and ``--port`` (default 9090); open the URL it
  prints in a browser. Ctrl-C or SIGTERM stops it.
* A missing file, a directory, or a file that does not start with Rerun's ``RRF`` magic is a
  one-line error (exit 2).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from types import FrameType

from agents import argtypes
from agents.errors import UserError

HELP = "open the Rerun viewer on a recording"

#: Every .rrd/.rbl file starts with ``RRF`` and a format digit (``RRF2`` in rerun 0.41).
RRD_MAGIC = b"RRF"
DEFAULT_WEB_PORT = 9090


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file", metavar="FILE.rrd",
        help="a Rerun recording (e.g. DIR/recording.rrd of `wiremap run --out DIR`)"
    )
    parser.add_argument(
        "--web", action="store_true",
        help="serve it with Rerun's web viewer instead of opening a window (the server keeps about "
        "one core busy even while idle: stop it with Ctrl-C when done)",
    )
    parser.add_argument(
        "--bind", default="127.0.0.1", metavar="IP", help="--web: address to serve on (default 127.0.0.1)"
    )
    parser.add_argument(
        "--port",
        type=argtypes.port,
        default=DEFAULT_WEB_PORT,
        metavar="P",
        help=f"--web: web viewer HTTP port (default {DEFAULT_WEB_PORT}; 0 picks a free one)",
    )


def find_rerun() -> str | None:
    """The ``rerun`` viewer executable.

    First the native binary inside the installed ``rerun_cli`` package: the ``rerun`` script in
    the venv's ``bin`` is a Python wrapper that runs that binary as a child, and a signal to the
    wrapper would orphan the viewer. Then a ``rerun`` beside this interpreter, then ``PATH``.
    """
    import importlib.util

    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin:
        pkg = Path(spec.origin).parent
        names = ["rerun.exe"] if sys.platform.startswith("win") else ["rerun"]
        if sys.platform == "darwin":
            names.insert(0, "Rerun.app/Contents/MacOS/Rerun")
        for name in names:
            cand = pkg / name
            if cand.is_file() and os.access(cand, os.X_OK):
                return str(cand)
    here = Path(sys.executable).parent
    return shutil.which("rerun", path=str(here)) or shutil.which("rerun")


def has_display(environ: dict[str, str] | None = None, platform: str | None = None) -> bool:
    """Whether a native window can open: always outside Linux/BSD; there, when ``DISPLAY`` or
    ``WAYLAND_DISPLAY`` is set and non-empty."""
    env = os.environ if environ is None else environ
    plat = sys.platform if platform is None else platform
    if not (plat.startswith("linux") or "bsd" in plat):
        return True
    return bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))


def check_recording(path: str | os.PathLike[str]) -> Path:
    """``path`` if it is a readable Rerun file, else ``UserError`` with the reason."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"{p}: no such file")
    if p.is_dir():
        raise UserError(f"{p}: is a directory, not a Rerun recording")
    try:
        with open(p, "rb") as fh:
            head = fh.read(4)
    except OSError as exc:
        raise UserError(f"{p}: {exc.strerror}") from None
    if not head.startswith(RRD_MAGIC):
        raise UserError(f"{p}: not a Rerun recording (.rrd files start with {RRD_MAGIC.decode()})")
    return p


def viewer_command(
    rerun: str, path: Path, web: bool, bind: str = "127.0.0.1", port: int = DEFAULT_WEB_PORT
) -> list[str]:
    """The command line that shows ``path``: the native viewer, or with ``web`` the web viewer
    served on ``bind:port`` (its gRPC proxy on a free port)."""
    if web:
        return [
            rerun,
            "--serve-web",
            "--bind",
            bind,
            "--web-viewer-port",
            str(port),
            "--port",
            "0",
            str(path),
        ]
    return [rerun, str(path)]


def _web_port(bind: str, port: int) -> int:
    """``port``, or with 0 a free one chosen here (so that the URL printed is the one served),
    after checking that ``bind`` is an address of this machine: one line, not the viewer's
    three-line error after the URL."""
    import socket

    try:
        with socket.socket(socket.AF_INET6 if ":" in bind else socket.AF_INET, socket.SOCK_STREAM) as s:
            # as the viewer's server binds: a port with connections in TIME_WAIT (a viewer just
            # stopped) is free to serve
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((bind, port))
            return int(s.getsockname()[1])
    except OSError as exc:
        raise UserError(f"--bind {bind} --port {port}: cannot serve there: {exc.strerror or exc}") from None


def run(args: argparse.Namespace) -> int:
    path = check_recording(args.file)
    if not args.web and not has_display():
        raise UserError(
            "no display (DISPLAY and WAYLAND_DISPLAY are unset), cannot open the viewer window: "
            f"serve it to a browser with `wiremap replay {path} --web`, "
            f"or summarise it with `rerun rrd stats {path}`"
        )
    rerun = find_rerun()
    if rerun is None:
        raise UserError("the `rerun` viewer is not installed (pip install rerun-sdk)")
    port = _web_port(args.bind, args.port) if args.web else args.port
    cmd = viewer_command(rerun, path, args.web, args.bind, port)
    if args.web:
        print(
            f"wiremap replay: serving {path} on http://{args.bind}:{port} (Rerun's server uses about "
            "a core even while idle; Ctrl-C stops it)",
            flush=True,
        )
    # the handlers first: a Ctrl-C that comes while the viewer starts still stops it cleanly
    child: subprocess.Popen[bytes] | None = None
    stopped = False

    def forward(signum: int, _frame: FrameType | None) -> None:
        nonlocal stopped
        stopped = True
        if child is not None and child.poll() is None:
            child.send_signal(signum)

    old = {s: signal.signal(s, forward) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            child = subprocess.Popen(cmd)
        except OSError as exc:
            raise UserError(f"cannot start {rerun}: {exc.strerror or exc}") from None
        if stopped:
            child.send_signal(signal.SIGINT)
        rc = child.wait()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if child is not None and child.poll() is None:
            child.kill()
            child.wait()
    # Stopped by our signal: a clean stop, not a failure.
    return 0 if rc in (-signal.SIGINT, -signal.SIGTERM, 130, 143) else rc
