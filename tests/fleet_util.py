"""Helpers for tests that use a real Zenoh router and real processes on 127.0.0.1.

Every helper cleans up after itself: processes are terminated and reaped (SIGTERM, then SIGKILL)
in ``finally`` blocks, sessions are closed by context managers. Ports are free ports found by
binding port 0. Waiting is on events with timeouts (:func:`wait_until` polls a condition with a
deadline only where no event exists, e.g. a file appearing).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import zenoh

from agents.bus import build_config, free_port, open_session, tcp_endpoint

REPO = Path(__file__).resolve().parent.parent
__all__ = [
    "REPO",
    "Fleet",
    "client",
    "free_port",
    "in_process_router",
    "spawn",
    "stop_process",
    "tcp_endpoint",
    "wait_until",
]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("RERUN_ANALYTICS", "0")
    return env


def spawn(args: Sequence[str], log: Path, cwd: Path | None = None) -> subprocess.Popen[bytes]:
    """Start ``python -m agents ARGS`` with stdout+stderr into ``log`` (no pipe to fill up)."""
    log.parent.mkdir(parents=True, exist_ok=True)
    fh = open(log, "wb")  # closed by stop_process (kept on the Popen object)
    try:
        p = subprocess.Popen(
            [sys.executable, "-m", "agents", *map(str, args)],
            stdout=fh,
            stderr=subprocess.STDOUT,
            cwd=str(cwd or REPO),
            env=_env(),
            start_new_session=True,
        )
    except BaseException:
        fh.close()
        raise
    p._wiremap_log = fh  # type: ignore[attr-defined]
    return p


def stop_process(p: subprocess.Popen[bytes], sig: int = signal.SIGTERM, timeout: float = 10.0) -> int | None:
    """Send ``sig``, wait up to ``timeout`` s, SIGKILL if still alive; always reaped.

    Returns the exit status after ``sig`` (None when it had to be killed)."""
    rc: int | None = None
    try:
        if p.poll() is None:
            try:
                p.send_signal(sig)
            except ProcessLookupError:
                pass
            try:
                rc = p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                rc = None
        else:
            rc = p.returncode
    finally:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                p.kill()
            p.wait(timeout=10)
        fh = getattr(p, "_wiremap_log", None)
        if fh is not None:
            fh.close()
    return rc


def log_text(p: subprocess.Popen[bytes], path: Path) -> str:
    fh = getattr(p, "_wiremap_log", None)
    if fh is not None and not fh.closed:
        fh.flush()
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def wait_until(cond: Callable[[], Any], timeout: float, what: str = "condition", step: float = 0.05) -> Any:
    """Poll ``cond`` until it returns a truthy value; raise ``TimeoutError`` after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(step)


@contextmanager
def in_process_router(port: int | None = None) -> Iterator[str]:
    """A Zenoh router session in this process on ``tcp/127.0.0.1:port``; yields the endpoint."""
    port = port or free_port()
    ep = tcp_endpoint(port)
    s = open_session(build_config("router", None, (), [ep]), wait=False)
    assert s is not None
    try:
        yield ep
    finally:
        s.close()


@contextmanager
def client(endpoint: str, timeout: float = 10.0) -> Iterator[zenoh.Session]:
    """A client session connected to ``endpoint``; closed on exit."""
    s = open_session(build_config("client", None, [endpoint]), timeout=timeout)
    assert s is not None
    try:
        yield s
    finally:
        s.close()


class Fleet:
    """Processes of one test; ``with Fleet(tmp) as f: f.start("r1", [...])`` stops them all
    (SIGTERM, then SIGKILL) and reaps them on exit, whatever happens."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = Path(tmp)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.exit_codes: dict[str, int | None] = {}

    def __enter__(self) -> Fleet:
        return self

    def __exit__(self, *_exc: object) -> None:
        errors: list[BaseException] = []
        threads = []
        for name in list(self.procs):
            t = threading.Thread(target=self._stop_quiet, args=(name, errors))
            t.start()
            threads.append(t)
        for t in threads:
            t.join()

    def _stop_quiet(self, name: str, errors: list[BaseException]) -> None:
        try:
            self.stop(name)
        except BaseException as exc:  # pragma: no cover - cleanup must go on
            errors.append(exc)

    def log_path(self, name: str) -> Path:
        return self.tmp / f"{name}.log"

    def start(self, name: str, args: Sequence[str]) -> subprocess.Popen[bytes]:
        p = spawn(args, self.log_path(name))
        self.procs[name] = p
        return p

    def stop(self, name: str, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int | None:
        p = self.procs.pop(name, None)
        if p is None:
            return self.exit_codes.get(name)
        rc = stop_process(p, sig, timeout)
        self.exit_codes[name] = rc
        return rc

    def log(self, name: str) -> str:
        return self.log_path(name).read_text(errors="replace") if self.log_path(name).exists() else ""

    def wait_log(self, name: str, text: str, timeout: float = 20.0) -> str:
        """Wait until ``text`` appears in the process's log (fails early if it exits)."""

        def check() -> bool:
            if text in self.log(name):
                return True
            p = self.procs.get(name)
            if p is not None and p.poll() is not None:
                raise AssertionError(f"{name} exited ({p.returncode}) before {text!r}:\n{self.log(name)}")
            return False

        wait_until(check, timeout, f"{text!r} in {name}'s log")
        return self.log(name)


def children_of(pid: int) -> list[int]:
    """Direct children of ``pid`` (from /proc; empty where /proc is missing)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == pid:
            out.append(int(d.name))
    return out


def alive(pid: int) -> bool:
    """Whether ``pid`` is a live (not zombie) process."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"
