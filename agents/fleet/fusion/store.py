"""The fusion service's store on disk: what :class:`StoreJob` writes, :class:`StoreWriter`
writing it in a background thread, :func:`read_store` reading it back, and the append-only
``latency.log``.

Files under the store directory: ``snapshot.msgpack`` (authoritative), ``robots/<id>.wfm``,
``fused.wfm``, ``state.json`` and ``latency.log`` (see :class:`StoreJob`).
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack

from agents.files.io import write_atomic, write_json
from agents.fleet.fusion.codec import decode_message, order_key
from mapping.se2 import Pose
from wire_codec.message import MapMessage

SNAPSHOT = "snapshot.msgpack"
LATENCY_LOG = "latency.log"
LATENCY_LOG_MAX_BYTES = 16 * 1024 * 1024  # rotated to latency.log.1 beyond this


@dataclass
class StoreJob:
    """One write of the fusion store, gathered by
    :meth:`~agents.fleet.fusion.state.FusionState.store_job`.

    :meth:`write` writes, in this order: the new latencies appended to ``latency.log``
    (:func:`append_latency_log`); then ``snapshot.msgpack``, the authoritative copy, in one
    atomic write (temporary file, fsync, rename): ``{"format": 2, "version", "stamp_ns",
    "robots": {id: bytes as received}, "fused": fused map bytes, "alignments": {id: [x, y,
    theta] or None}}``, so a crash at any moment leaves either the old or the new snapshot;
    then views for people and tools, each atomic too: ``robots/<id>.wfm`` (those in
    :attr:`views`), ``fused.wfm`` and ``state.json`` (version, per-robot seq/boot/sha256,
    counters with the latency summary, ``latency_total``). ``state.json`` comes last, so a
    reader that sees its ``latency_total`` finds that many lines in the log.
    """

    store: Path
    version: int
    stamp_ns: int
    robots: dict[str, bytes]
    views: set[str]
    fused_raw: bytes
    alignments: dict[str, list[float] | None]
    state: dict[str, Any]
    latencies: list[tuple[int, float, int]]

    def then(self, newer: StoreJob) -> StoreJob:
        """This job followed by ``newer`` as one: newer contents, the views and latencies of both."""
        return StoreJob(
            newer.store, newer.version, newer.stamp_ns, newer.robots, self.views | newer.views, newer.fused_raw,
            newer.alignments, newer.state, self.latencies + newer.latencies,
        )

    def write(self) -> None:
        """Write the files, in the order given above (raises ``OSError``)."""
        d = self.store
        if self.latencies:
            append_latency_log(d, self.latencies)
        snap = {
            "format": 2,
            "version": self.version,
            "stamp_ns": self.stamp_ns,
            "robots": self.robots,
            "fused": self.fused_raw,
            "alignments": self.alignments,
        }
        write_atomic(d / SNAPSHOT, bytes(msgpack.packb(snap, use_bin_type=True)))
        for rid in sorted(self.views):
            if rid in self.robots:
                write_atomic(d / "robots" / f"{rid}.wfm", self.robots[rid])
        write_atomic(d / "fused.wfm", self.fused_raw)
        write_json(d / "state.json", self.state)


def append_latency_log(store: str | os.PathLike[str], samples: list[tuple[int, float, int]]) -> None:
    """Append ``<index> <ms> <published_ns>`` lines to ``<store>/latency.log`` (no fsync:
    statistics, not state); rotate it to ``latency.log.1`` first when it is over
    ``LATENCY_LOG_MAX_BYTES``. ``index`` counts every sample ever recorded (1, 2, ...),
    ``published_ns`` is the wall clock of the fused publish the sample ended at."""
    d = Path(store)
    d.mkdir(parents=True, exist_ok=True)
    path = d / LATENCY_LOG
    try:
        if path.stat().st_size > LATENCY_LOG_MAX_BYTES:
            os.replace(path, d / (LATENCY_LOG + ".1"))
    except FileNotFoundError:
        pass
    text = "".join(f"{i} {v:.3f} {t}\n" for i, v, t in samples)
    with open(path, "a", encoding="ascii") as fh:
        fh.write(text)


def read_latency_log(store: str | os.PathLike[str], last: int) -> list[tuple[int, float]]:
    """The last ``last`` ``(index, ms)`` samples of ``<store>/latency.log`` (and of
    ``latency.log.1`` when the current file holds fewer); unreadable lines are skipped."""
    d = Path(store)
    out: list[tuple[int, float]] = []
    for name in (LATENCY_LOG, LATENCY_LOG + ".1"):
        need = last - len(out)
        if need <= 0:
            break
        try:
            with open(d / name, "rb") as fh:
                size = fh.seek(0, os.SEEK_END)
                start = max(0, size - need * 24)
                fh.seek(start)
                data = fh.read()
        except OSError:
            continue
        lines = data.split(b"\n")
        if start > 0:
            lines = lines[1:]  # probably cut
        got: list[tuple[int, float]] = []
        for ln in lines:
            parts = ln.split()
            if len(parts) not in (2, 3):
                continue
            try:
                got.append((int(parts[0]), float(parts[1])))
            except ValueError:
                continue
        out = got[max(0, len(got) - need) :] + out
    return out


@dataclass(frozen=True)
class StoreContents:
    """What :func:`read_store` found: the stored version, the stored fused map (None if
    unreadable), each robot's stored bytes, and the alignments the stored map was fused with
    (None when not stored: a format-1 snapshot or the views)."""

    version: int
    fused: MapMessage | None
    raw_robots: dict[str, bytes]
    from_snapshot: bool
    alignments: dict[str, Pose | None] | None = None

    def robots(self) -> dict[str, MapMessage]:
        """The stored robot maps, decoded (undecodable ones left out)."""
        out = {}
        for rid, raw in self.raw_robots.items():
            try:
                out[rid] = decode_message(raw)
            except ValueError:
                continue
        return out


def _read_alignments(doc: Any) -> dict[str, Pose | None] | None:
    if not isinstance(doc, dict):
        return None
    out: dict[str, Pose | None] = {}
    for rid, v in doc.items():
        if not isinstance(rid, str):
            return None
        if v is None:
            out[rid] = None
            continue
        if not (isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) for x in v)):
            return None
        try:
            out[rid] = Pose(float(v[0]), float(v[1]), float(v[2]))
        except ValueError:
            return None
    return out


def read_store(store: str | os.PathLike[str], warn: Callable[[str], None] | None = None) -> StoreContents:
    """Read a fusion store without fusing anything (for
    :meth:`~agents.fleet.fusion.state.FusionState.load`, tests and tools).

    ``snapshot.msgpack`` is used when it is readable and the ``robots/*.wfm`` views agree
    with it: every view file decodes and is the snapshot's map of that robot or an older one
    of it (a save interrupted between the snapshot and the views leaves older views). A view
    that is newer, unreadable or not in the snapshot was changed by hand, and then the views
    win (``robots/*.wfm``, ``fused.wfm``, ``state.json``), unreadable files skipped with a
    warning.
    """
    d = Path(store)
    say = warn or (lambda _t: None)
    views: dict[str, bytes] = {}
    for f in sorted((d / "robots").glob("*.wfm")):
        try:
            views[f.stem] = f.read_bytes()
        except OSError as exc:
            views[f.stem] = b""
            say(f"cannot read {f}: {exc}")
    snap_path = d / SNAPSHOT
    if snap_path.is_file():
        try:
            snap = msgpack.unpackb(snap_path.read_bytes(), raw=False)
            robots = snap["robots"]
            if not (isinstance(robots, dict) and all(isinstance(k, str) and isinstance(v, bytes) for k, v in robots.items())):
                raise ValueError("robots is not a map of id -> bytes")
            version = int(snap["version"])
            fused: MapMessage | None = None
            try:
                fused = decode_message(snap["fused"])
            except (ValueError, TypeError):
                say(f"{snap_path}: the fused map in it is unreadable")
            hand_edited = _views_disagree(robots, views)
            if hand_edited is None:
                al = _read_alignments(snap.get("alignments"))
                return StoreContents(version, fused, dict(sorted(robots.items())), True, al)
            say(f"{hand_edited}: using robots/*.wfm rather than {SNAPSHOT}")
        except (OSError, ValueError, TypeError, KeyError, msgpack.UnpackException) as exc:
            say(f"{snap_path} is unreadable ({type(exc).__name__}: {exc}); using robots/*.wfm")
    raw: dict[str, bytes] = {}
    for rid, data in views.items():
        try:
            decode_message(data)
        except ValueError as exc:
            say(f"skipping {d / 'robots' / (rid + '.wfm')}: {exc}")
            continue
        raw[rid] = data
    version = 0
    try:
        version = int(json.loads((d / "state.json").read_text()).get("version", 0))
    except (OSError, ValueError, TypeError, AttributeError):
        pass
    fused = None
    try:
        fused = decode_message((d / "fused.wfm").read_bytes())
        version = max(version, int(fused.seq))
    except (OSError, ValueError):
        pass
    return StoreContents(version, fused, raw, False)


def _views_disagree(snapshot: dict[str, bytes], views: dict[str, bytes]) -> str | None:
    """Why the ``robots/*.wfm`` views cannot come from a (possibly interrupted) save of
    ``snapshot``, or None when they can."""
    for rid, data in views.items():
        if rid not in snapshot:
            return f"robots/{rid}.wfm is not in the snapshot"
        if data == snapshot[rid]:
            continue
        try:
            view_key = order_key(decode_message(data), data)
            snap_key = order_key(decode_message(snapshot[rid]), snapshot[rid])
        except ValueError:
            return f"robots/{rid}.wfm is unreadable"
        if view_key > snap_key:
            return f"robots/{rid}.wfm is newer than the snapshot"
    return None


class StoreWriter:
    """Writes :class:`StoreJob` s in a background thread, so that the fusion loop never waits
    for a disk (each store write fsyncs several files).

    :meth:`submit` hands over a job; a job still waiting when the next arrives is combined
    with it (:meth:`StoreJob.then`: the newest contents, every view and latency of both), so
    at most one write is ever queued and the files are written in order. :meth:`close` writes
    what is waiting and stops the thread. A failed write is reported through ``say`` (once per
    error message) and counted in :attr:`errors`; the next job writes everything again.
    """

    def __init__(self, say: Callable[[str], None] | None = None) -> None:
        self.say = say or (lambda _s: None)
        self._cond = threading.Condition()
        self._job: StoreJob | None = None
        self._busy = False
        self._stop = False
        self.errors = 0
        self.written = 0
        self._last_error = ""
        self._thread = threading.Thread(target=self._run, name="fusion-store", daemon=True)
        self._thread.start()

    def submit(self, job: StoreJob) -> None:
        """Hand over ``job`` (combined with a job still waiting, if any)."""
        with self._cond:
            self._job = job if self._job is None else self._job.then(job)
            self._cond.notify_all()

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._job is None and not self._stop:
                    self._cond.wait()
                job, self._job = self._job, None
                if job is None:
                    return
                self._busy = True
            try:
                job.write()
                self.written += 1
            except OSError as exc:
                self.errors += 1
                text = f"cannot write the store {job.store}: {exc}"
                if text != self._last_error:
                    self._last_error = text
                    self.say(text)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until nothing is queued or being written; returns whether that happened."""
        with self._cond:
            return self._cond.wait_for(lambda: self._job is None and not self._busy, timeout)

    def close(self, timeout: float = 30.0) -> None:
        """Write what is waiting, then stop the thread (waits up to ``timeout`` seconds)."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout)
