"""Helpers for tests that use a real Zenoh router and real processes on 127.0.0.1.

Every helper cleans up after itself: processes are terminated and reaped (SIGTERM, then SIGKILL)
in ``finally`` blocks, sessions are closed by context managers. Ports are free ports found by
binding port 0. Waiting is on events with timeouts (:func:`wait_until` polls a condition with a
deadline only where no event exists, e.g. a file appearing).
"""

from __future__ import annotations

import json
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

from agents.fleet import proc
from agents.fleet.bus import FleetKeys, build_config, free_port, open_session, tcp_endpoint

REPO = Path(__file__).resolve().parent.parent
__all__ = [
    "REPO",
    "Fleet",
    "FusedWatcher",
    "client",
    "free_port",
    "in_process_router",
    "query_fused",
    "query_stats",
    "record",
    "rss_kb",
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
def client(
    endpoint: str, timeout: float = 10.0, credentials: str | Path | None = None
) -> Iterator[zenoh.Session]:
    """A client session connected to ``endpoint`` (with a credentials file, if given); closed
    on exit."""
    cfg = build_config("client", None, [endpoint])
    if credentials is not None:
        from agents.fleet.secure import apply_credentials, load_credentials

        apply_credentials(cfg, load_credentials(credentials))
    s = open_session(cfg, timeout=timeout)
    assert s is not None
    try:
        yield s
    finally:
        s.close()


class FusedWatcher:
    """Subscribes to the fused map and keeps every decoded message with its arrival time
    (``monotonic``); waits on a condition variable, never on fixed sleeps."""

    def __init__(self, session: zenoh.Session, keys: FleetKeys) -> None:
        from agents.fleet.fusion import decode_message

        self._decode = decode_message
        self.msgs: list[Any] = []
        self.times: list[float] = []
        self.cond = threading.Condition()
        self.sub = session.declare_subscriber(keys.fused_map, self._cb)

    def _cb(self, sample: zenoh.Sample) -> None:
        m = self._decode(sample.payload.to_bytes())
        with self.cond:
            self.msgs.append(m)
            self.times.append(time.monotonic())
            self.cond.notify_all()

    def count(self) -> int:
        with self.cond:
            return len(self.msgs)

    def wait_for(self, pred: Callable[[Any], bool], timeout: float, what: str, since: int = 0) -> Any:
        """The newest message (from index ``since`` on) that satisfies ``pred``."""
        return self._wait(pred, timeout, what, since, newest=True)[0]

    def wait_for_timed(
        self, pred: Callable[[Any], bool], timeout: float, what: str, since: int = 0
    ) -> tuple[Any, float]:
        """The *first* message (from index ``since`` on) that satisfies ``pred``, with its
        arrival time."""
        return self._wait(pred, timeout, what, since, newest=False)

    def _wait(
        self, pred: Callable[[Any], bool], timeout: float, what: str, since: int, newest: bool
    ) -> tuple[Any, float]:
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                order = range(len(self.msgs) - 1, since - 1, -1) if newest else range(since, len(self.msgs))
                for i in order:
                    if pred(self.msgs[i]):
                        return self.msgs[i], self.times[i]
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no fused map with {what} in {timeout} s (got {len(self.msgs)})")
                self.cond.wait(left)

    def close(self) -> None:
        self.sub.undeclare()


def query_fused(session: zenoh.Session, keys: FleetKeys, timeout: float = 1.0) -> Any:
    """The fused map the fusion service's queryable answers with, or None."""
    from agents.fleet.fusion import decode_message

    for reply in session.get(keys.fused_map, timeout=timeout):
        if reply.ok is not None:
            return decode_message(reply.ok.payload.to_bytes())
    return None


def query_stats(session: zenoh.Session, keys: FleetKeys, timeout: float = 1.0) -> dict[str, Any] | None:
    """The fusion service's counters document (``wiremap/<fleet>/fused/stats``), or None."""
    for reply in session.get(keys.fusion_stats, timeout=timeout):
        if reply.ok is not None:
            doc: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return doc
    return None


def rss_kb(pid: int) -> int:
    """Resident set size of ``pid`` in KiB (:func:`agents.fleet.proc.rss_kb`, which must know it)."""
    kb = proc.rss_kb(pid)
    if kb is None:
        raise RuntimeError(f"no VmRSS for {pid}")
    return kb


def record(record_property: Callable[[str, Any], None] | None, name: str, value: Any) -> None:
    """Report a measured figure: a junit property and a line on stdout (``pytest -s`` or the
    captured output of a failing test shows it)."""
    if record_property is not None:
        record_property(name, value)
    print(f"FIGURE {name} = {value}", flush=True)


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

    def kill9(self, name: str) -> float:
        """SIGKILL the process group of ``name`` at once and reap it; returns the monotonic time
        just before the signal."""
        p = self.procs.pop(name)
        t = time.monotonic()
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        p.wait(timeout=10)
        fh = getattr(p, "_wiremap_log", None)
        if fh is not None:
            fh.close()
        self.exit_codes[name] = p.returncode
        return t

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
