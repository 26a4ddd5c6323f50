"""The fusion service's store on disk: what :class:`StoreJob` writes, :class:`StoreWriter`
writing it in a background thread, :func:`read_store` reading it back, and the append-only
``latency.log``.

Files under the store directory: ``snapshot.msgpack`` (authoritative), ``robots/<id>.wfm``,
``fused.wfm``, ``state.json`` and ``latency.log`` (see :class:`StoreJob`).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, Self

import msgpack

from agents.errors import UserError
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
    extra: dict[str, Any] = field(default_factory=dict)
    forgotten: set[str] = field(default_factory=set)

    def then(self, newer: StoreJob) -> StoreJob:
        """This job followed by ``newer`` as one: newer contents, the views and latencies of both."""
        return StoreJob(
            newer.store, newer.version, newer.stamp_ns, newer.robots, self.views | newer.views,
            newer.fused_raw, newer.alignments, newer.state, self.latencies + newer.latencies, newer.extra,
            (self.forgotten | newer.forgotten) - set(newer.robots),
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
            "extra": self.extra,
        }
        write_atomic(d / SNAPSHOT, seal_snapshot(bytes(msgpack.packb(snap, use_bin_type=True))))
        for rid in sorted(self.views):
            if rid in self.robots:
                write_atomic(d / "robots" / f"{rid}.wfm", self.robots[rid])
        for name in self.forgotten:
            try:
                (d / "robots" / f"{name}.wfm").unlink()
            except FileNotFoundError:
                pass
        write_atomic(d / "fused.wfm", self.fused_raw)
        write_json(d / "state.json", seal_json(self.state))


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


SNAPSHOT_MAGIC = b"WMSNAP3\n"  # then the sha256 of the body (32 bytes), then the msgpack body
MAX_VERSION = (1 << 63) - 1


class StoreDamaged(UserError):
    """The store cannot give back what it held (no version, or a robot map lost):
    ``wiremap fuse`` says so in one line and exits 2, unless ``--reset``."""


def seal_snapshot(body: bytes) -> bytes:
    """``SNAPSHOT_MAGIC``, the sha256 of ``body``, ``body``."""
    return SNAPSHOT_MAGIC + hashlib.sha256(body).digest() + body


def unseal_snapshot(data: bytes) -> bytes:
    """The body of a sealed snapshot; raises ``ValueError`` when the checksum does not match.
    A snapshot written before the seal (plain msgpack) is returned as it is."""
    if not data.startswith(SNAPSHOT_MAGIC):
        if data[:1] in (b"\x86", b"\x87", b"\xde"):  # a msgpack map: a format-2 snapshot from before
            return data
        raise ValueError("not a snapshot")
    n = len(SNAPSHOT_MAGIC)
    digest, body = data[n : n + 32], data[n + 32 :]
    if hashlib.sha256(body).digest() != digest:
        raise ValueError("checksum mismatch")
    return body


def seal_json(doc: dict[str, Any]) -> dict[str, Any]:
    """``doc`` with ``"sha256"``: the digest of its canonical JSON without that field."""
    body = {k: v for k, v in doc.items() if k != "sha256"}
    return {**body, "sha256": hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()}


def unseal_json(text: str) -> dict[str, Any]:
    """A document written by :func:`seal_json`; ``ValueError`` when it is not one or the digest
    does not match."""
    doc = json.loads(text)
    if not isinstance(doc, dict) or "sha256" not in doc:
        raise ValueError("no checksum")
    if seal_json(doc)["sha256"] != doc["sha256"]:
        raise ValueError("checksum mismatch")
    return doc


@dataclass(frozen=True)
class StoreContents:
    """What :func:`read_store` found: the stored version, the stored fused map (None if
    unreadable), each robot's stored bytes, and the alignments the stored map was fused with
    (None when not stored or not trusted). ``damaged`` lists what was wrong and how it was
    recovered (one line each); ``rewrite`` the robots whose view file must be written again;
    ``extra`` what the snapshot keeps besides the maps (per-robot history, forgotten ids)."""

    version: int
    fused: MapMessage | None
    raw_robots: dict[str, bytes]
    from_snapshot: bool
    alignments: dict[str, Pose | None] | None = None
    damaged: tuple[str, ...] = ()
    rewrite: frozenset[str] = frozenset()
    extra: dict[str, Any] = field(default_factory=dict)

    def robots(self) -> dict[str, MapMessage]:
        """The stored robot maps, decoded (undecodable ones left out)."""
        out = {}
        for rid, raw in self.raw_robots.items():
            try:
                out[rid] = decode_message(raw)
            except ValueError:
                continue
        return out


def _read_alignments(doc: Any, max_m: float = 10.0, max_rad: float = 1.0) -> dict[str, Pose | None] | None:
    """Stored ICP corrections; None (recompute them) unless each is finite and small."""
    if not isinstance(doc, dict):
        return None
    out: dict[str, Pose | None] = {}
    for rid, v in doc.items():
        if not isinstance(rid, str):
            return None
        if v is None:
            out[rid] = None
            continue
        if not (
            isinstance(v, list)
            and len(v) == 3
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        ):
            return None
        if math.hypot(v[0], v[1]) > max_m or abs(v[2]) > max_rad:
            return None
        out[rid] = Pose(float(v[0]), float(v[1]), float(v[2]))
    return out


def _version(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= MAX_VERSION:
        raise ValueError(f"version {str(v)[:40]} is not in [0, 2^63)")
    return int(v)


def _valid_map(raw: bytes, rid: str) -> tuple[int, int, str] | None:
    """The order key of a stored robot map that decodes and is from ``rid``, else None."""
    from agents.fleet.bus import valid_name

    if not valid_name(rid):
        return None
    try:
        msg = decode_message(raw)
    except (ValueError, TypeError):
        return None
    if msg.sender != rid:
        return None
    return order_key(msg, raw)


def read_store(store: str | os.PathLike[str], warn: Callable[[str], None] | None = None) -> StoreContents:
    """Read a fusion store without fusing anything (for
    :meth:`~agents.fleet.fusion.state.FusionState.load`, tests and tools).

    Every file is checked: ``snapshot.msgpack`` by its sha256 seal and its fields (version in
    ``[0, 2^63)``, robots a map of id -> bytes, corrections finite and small), ``state.json``
    by its sha256, each ``robots/<id>.wfm`` and ``fused.wfm`` by the codec's CRC and decoding.
    For each robot the newest copy that passes (snapshot or view) is taken: a view older than
    the snapshot is an interrupted save, a newer one an edit by hand; a damaged view is
    recovered from the snapshot and written again. When the snapshot is damaged, the views are
    used, and every robot ``state.json`` lists must be among them. The version is the largest
    the snapshot, ``state.json`` and ``fused.wfm`` agree on.

    Raises
    ------
    StoreDamaged
        When the store held something but its version cannot be known (every file that holds
        one is damaged), or a robot map it recorded is lost: starting would serve a map that
        forgot walls, or versions going backwards.
    """
    d = Path(store)
    say = warn or (lambda _t: None)
    damaged: list[str] = []

    def note(text: str) -> None:
        damaged.append(text)
        say(text)

    # ---- the snapshot
    snap: dict[str, Any] | None = None
    snap_path = d / SNAPSHOT
    present = snap_path.is_file()
    if present:
        try:
            doc = msgpack.unpackb(unseal_snapshot(snap_path.read_bytes()), raw=False, strict_map_key=False)
            if not isinstance(doc, dict):
                raise ValueError("not a map")
            robots = doc["robots"]
            if not (
                isinstance(robots, dict)
                and all(isinstance(k, str) and isinstance(v, bytes) for k, v in robots.items())
            ):
                raise ValueError("robots is not a map of id -> bytes")
            doc["version"] = _version(doc["version"])
            snap = doc
        except (OSError, ValueError, TypeError, KeyError, msgpack.UnpackException) as exc:
            note(f"{snap_path} is damaged ({type(exc).__name__}: {exc}); recovering from the other files")

    # ---- state.json and fused.wfm: versions, and the robots the store recorded
    state: dict[str, Any] | None = None
    state_path = d / "state.json"
    if state_path.is_file():
        present = True
        try:
            state = unseal_json(state_path.read_text())
            _version(state.get("version"))
        except (OSError, ValueError, TypeError, UnicodeDecodeError) as exc:
            state = None
            note(f"{state_path} is damaged ({type(exc).__name__}: {exc})")
    fused: MapMessage | None = None
    fused_path = d / "fused.wfm"
    if fused_path.is_file():
        present = True
        try:
            fused = decode_message(fused_path.read_bytes())
            _version(fused.seq)
        except (OSError, ValueError, TypeError) as exc:
            fused = None
            note(f"{fused_path} is damaged ({type(exc).__name__}: {exc})")

    # ---- the views
    views: dict[str, bytes] = {}
    rewrite: set[str] = set()
    for f in sorted((d / "robots").glob("*.wfm")) if (d / "robots").is_dir() else []:
        present = True
        try:
            data = f.read_bytes()
        except OSError as exc:
            data = b""
            note(f"cannot read {f}: {exc}")
        if _valid_map(data, f.stem) is None:
            note(f"{f} is damaged or not a map of {f.stem!r}")
            rewrite.add(f.stem)
            continue
        views[f.stem] = data

    if not present:
        return StoreContents(0, None, {}, False)

    raw: dict[str, bytes] = {}
    snap_robots: dict[str, bytes] = dict(snap["robots"]) if snap is not None else {}
    for rid, data in snap_robots.items():
        if _valid_map(data, rid) is None:
            note(f"{SNAPSHOT}: the map of {rid!r} in it is damaged")
            continue
        raw[rid] = data
    for rid, data in views.items():
        have = raw.get(rid)
        if have is None or (have != data and (_valid_map(data, rid) or ()) > (_valid_map(have, rid) or ())):
            if snap is not None:
                say(f"robots/{rid}.wfm is newer than {SNAPSHOT} (edited by hand?): using it")
            raw[rid] = data
    for rid in rewrite:
        if rid in raw:
            say(f"robots/{rid}.wfm recovered from {SNAPSHOT}")
    extra = snap.get("extra") if snap is not None else None
    extra = extra if isinstance(extra, dict) else {}
    got = extra.get("forgotten")
    forgotten: dict[str, Any] = got if isinstance(got, dict) else {}

    # ---- what must not be lost
    versions: list[int] = []
    if snap is not None:
        versions.append(snap["version"])
    if state is not None:
        versions.append(int(state["version"]))
    if fused is not None:
        versions.append(int(fused.seq))
    if not versions:
        raise StoreDamaged(
            f"the store {d} is damaged beyond recovery (no readable snapshot, state.json or fused.wfm: "
            "the version would go backwards); move it aside or start with --reset"
        )
    recorded = state.get("robots") if state is not None else None
    if snap is None and isinstance(recorded, dict):
        lost = sorted(r for r in recorded if isinstance(r, str) and r not in raw and r not in forgotten)
        if lost:
            raise StoreDamaged(
                f"the store {d} lost the maps of {' '.join(lost)} (snapshot and views damaged); "
                "move it aside or start with --reset"
            )
    if snap is not None:
        for rid in snap_robots:
            if rid not in raw:
                raise StoreDamaged(
                    f"the store {d} lost the map of {rid} (damaged in the snapshot, no good view); "
                    "move it aside or start with --reset"
                )
    al = None
    if snap is not None and raw == snap_robots:
        al = _read_alignments(snap.get("alignments"))
        if al is None and snap.get("alignments") is not None:
            note(f"{SNAPSHOT}: the stored alignments are out of range; recomputing them")
    if snap is not None:  # the snapshot's fused map is the one its robots and alignments make
        try:
            fused = decode_message(snap["fused"])
        except (ValueError, TypeError, KeyError):
            note(f"{SNAPSHOT}: the fused map in it is damaged")
    return StoreContents(
        max(versions), fused, dict(sorted(raw.items())), snap is not None, al, tuple(damaged),
        frozenset(r for r in rewrite if r in raw), extra,
    )


class WriteJob(Protocol):
    """What :class:`StoreWriter` writes: :class:`StoreJob`, or the root's files."""

    store: Path
    version: int

    def then(self, newer: Self) -> Self: ...

    def write(self) -> None: ...


class StoreWriter:
    """Writes :class:`StoreJob` s (any :class:`WriteJob`) in a background thread, so that the
    fusion loop never waits for a disk (each store write fsyncs several files).

    :meth:`submit` hands over a job; a job still waiting when the next arrives is combined
    with it (:meth:`StoreJob.then`: the newest contents, every view and latency of both), so
    at most one write is ever queued and the files are written in order. :meth:`close` writes
    what is waiting and stops the thread. A failed write is reported through ``say`` (once per
    error message) and counted in :attr:`errors`; the next job writes everything again.
    """

    def __init__(self, say: Callable[[str], None] | None = None) -> None:
        self.say = say or (lambda _s: None)
        self._cond = threading.Condition()
        self._job: WriteJob | None = None
        self._busy = False
        self._stop = False
        self.errors = 0
        self.written = 0
        self.written_version = 0  # the version of the last snapshot written
        self.ok = True  # the last write succeeded
        self._last_error = ""
        self._thread = threading.Thread(target=self._run, name="fusion-store", daemon=True)
        self._thread.start()

    def submit(self, job: WriteJob) -> None:
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
                self.written_version = job.version
                if not self.ok:
                    self.say(f"the store {job.store} is written again (v{job.version})")
                self.ok = True
                self._last_error = ""
            except OSError as exc:
                self.errors += 1
                self.ok = False
                text = f"cannot write the store {job.store}: {exc}"
                if text != self._last_error:
                    self._last_error = text
                    self.say(text)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    @property
    def last_error(self) -> str:
        return self._last_error

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
