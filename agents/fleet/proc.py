"""Processes: stopping a group of children together, freezing this one's heap, and what
``/proc`` says about a process (resident memory, CPU time)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Mapping, Sequence
from pathlib import Path


def stop_processes(
    procs: Mapping[str, subprocess.Popen[bytes]], names: Sequence[str], timeout: float
) -> dict[str, int | None]:
    """SIGINT to ``names`` together, wait up to ``timeout`` seconds for all of them (one shared
    deadline), then SIGKILL the process group of any still running; every one is reaped.
    Returns the exit codes (None: had to be killed)."""
    for n in names:
        p = procs[n]
        if p.poll() is None:
            try:
                p.send_signal(signal.SIGINT)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + timeout
    codes: dict[str, int | None] = {}
    for n in names:
        p = procs[n]
        try:
            codes[n] = p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                p.kill()
            p.wait()
            codes[n] = None
    return codes


def freeze_heap() -> None:
    """Move every object alive now (modules, the loaded state) out of the garbage collector's
    reach (``gc.freeze``), after a full collection. A long-running loop then pays for its own
    objects only: the full collections of a fusion service with numpy, scipy and zenoh loaded
    took 26-35 ms each, a stall every few seconds in the publish latency."""
    import gc

    gc.collect()
    gc.freeze()


_PAGE_KB = (os.sysconf("SC_PAGE_SIZE") // 1024) if hasattr(os, "sysconf") else 4


def rss_kb(pid: int | str = "self") -> int | None:
    """Resident set size of a process in KiB (``VmRSS`` in ``/proc``; None elsewhere).

    Read from ``/proc/<pid>/statm`` (resident pages, the same counter as ``VmRSS``; a third of
    the cost of ``status``, and the service reports it with every new version), else from
    ``status``."""
    try:
        with open(f"/proc/{pid}/statm", "rb") as fh:
            return int(fh.read().split()[1]) * _PAGE_KB
    except (OSError, ValueError, IndexError):
        pass
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def cpu_seconds(pid: int | str = "self") -> float | None:
    """User + system CPU seconds of a live process (``/proc/<pid>/stat``; None when it is gone or
    ``/proc`` is absent)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None
