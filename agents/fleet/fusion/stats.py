"""The fusion service's counters and publish latencies (served on ``fused/stats`` and written to
the store's ``state.json``)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

MAX_LATENCIES = 100_000  # latencies kept in the window (the all-time count is kept apart)


class LatencyWindow:
    """Publish latencies (ms): the last ``capacity`` in a ring buffer plus an all-time count.

    ``total`` counts every sample ever added (also across a restart when restored), so a reader
    can tell how many were recorded between two looks even when the window is full; the
    summary (:meth:`summary`) is over the window and cached until asked for a fresh one.
    """

    def __init__(self, capacity: int = MAX_LATENCIES) -> None:
        self.capacity = int(capacity)
        self._buf = np.zeros(self.capacity, dtype=np.float64)
        self._at = np.zeros(self.capacity, dtype=np.int64)  # when each was recorded (ns, 0: unknown)
        self._n = 0  # samples in the window
        self._head = 0  # next write position
        self.total = 0
        self._summary: dict[str, float | int | None] | None = None

    def extend(self, values: Iterable[float], at_ns: int = 0) -> None:
        """Add samples recorded at ``at_ns`` (wall clock, ns; 0: unknown)."""
        for v in values:
            self._buf[self._head] = float(v)
            self._at[self._head] = int(at_ns)
            self._head = (self._head + 1) % self.capacity
            self._n = min(self._n + 1, self.capacity)
            self.total += 1

    def _ordered(self, a: np.ndarray) -> np.ndarray:
        if self._n < self.capacity:
            return a[: self._n].copy()
        return np.concatenate([a[self._head :], a[: self._head]])

    def values(self) -> np.ndarray:
        """The window, oldest first (a copy)."""
        return self._ordered(self._buf)

    def tail(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The last ``min(k, len)`` samples and their record times (ns), oldest first."""
        v, t = self.values(), self._ordered(self._at)
        k = min(max(0, k), len(v))
        return v[len(v) - k :], t[len(t) - k :]

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[float]:
        return iter(self.values().tolist())

    def __eq__(self, other: object) -> bool:
        if isinstance(other, LatencyWindow):
            return self.total == other.total and np.array_equal(self.values(), other.values())
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]

    def summary(self, fresh: bool = True) -> dict[str, float | int | None]:
        """``{n, total, p50, p99, max}`` over the window; ``fresh=False`` returns the summary
        computed last time (with the current ``n`` and ``total``) unless there is none."""
        if fresh or self._summary is None:
            self._summary = latency_summary(self.values())
        out = dict(self._summary)
        out["n"] = self._n
        out["total"] = self.total
        return out


@dataclass
class FusionStats:
    """Counters of the fusion service (one process lifetime; see :mod:`agents.fleet.fusion`).

    received : payloads offered to :meth:`~agents.fleet.fusion.state.FusionState.offer` (decoded or not).
    accepted : became their robot's latest map; duplicates / outdated: identical to, or older
        than, the latest (not errors: maps are re-sent).
    superseded : not decoded because a newer payload of the same robot key came in the same
        drained batch (maps are whole states; only the header was read, see
        :meth:`~agents.fleet.fusion.state.FusionState.offer_latest`); counted in ``received``.
    same_body : of the payloads decoded, those whose body was byte for byte the body of their
        robot's latest accepted map (a map sent again): the body was not read again and the
        values computed from its arrays were reused (:meth:`~agents.fleet.fusion.state.FusionState.offer`);
        a cost counter (each is also counted under its outcome: ``accepted``, ``duplicates``,
        ``absurd``, ...).
    quarantined : kept aside as inconsistent with the robot's history or the fleet, not merged
        (:mod:`agents.fleet.fusion.quarantine`); ``quarantined_by`` by reason.
    held : maps that waited because their robot's fusion work budget was spent
        (:mod:`agents.fleet.fusion.budget`; fused later, the latest one per robot).
    malformed / rejected / absurd : dropped in :meth:`~agents.fleet.fusion.state.FusionState.offer`; ``*_by``
    break them
        down by codec error class or reason.
    oversized / rate_limited / overflow : dropped by :class:`~agents.fleet.fusion.intake.Intake` before
    decoding.
    side_dropped : pose and visualisation payloads dropped (too big, bad key, a field that fails
        :mod:`agents.fleet.validate`); ``side_dropped_by`` by ``<kind>_<reason>``.
    published : fused versions published.
    fuses / full_fuses : fused maps computed (fast path) / of them, full recomputes.
    alignments : ICP alignments run (the slow path).
    latencies_ms : the publish latencies (:class:`LatencyWindow`; ``latency_total`` counts all).
    """

    received: int = 0
    accepted: int = 0
    duplicates: int = 0
    outdated: int = 0
    superseded: int = 0
    same_body: int = 0
    malformed: int = 0
    rejected: int = 0
    absurd: int = 0
    quarantined: int = 0
    held: int = 0
    oversized: int = 0
    rate_limited: int = 0
    overflow: int = 0
    side_dropped: int = 0
    published: int = 0
    fuses: int = 0
    full_fuses: int = 0
    alignments: int = 0
    malformed_by: dict[str, int] = field(default_factory=dict)
    rejected_by: dict[str, int] = field(default_factory=dict)
    absurd_by: dict[str, int] = field(default_factory=dict)
    quarantined_by: dict[str, int] = field(default_factory=dict)
    side_dropped_by: dict[str, int] = field(default_factory=dict)
    latencies_ms: LatencyWindow = field(default_factory=LatencyWindow)

    @property
    def dropped(self) -> int:
        """Every map payload that was dropped, for whatever reason."""
        return (
            self.malformed + self.rejected + self.absurd + self.oversized + self.rate_limited + self.overflow
        )

    @property
    def latency_total(self) -> int:
        return self.latencies_ms.total

    def as_dict(self, fresh_latency: bool = True) -> dict[str, Any]:
        """The counters as JSON-ready values. ``fresh_latency=False`` reuses the last latency
        percentiles (computing them over 100,000 samples takes milliseconds)."""
        return {
            "received": self.received,
            "accepted": self.accepted,
            "duplicates": self.duplicates,
            "outdated": self.outdated,
            "superseded": self.superseded,
            "same_body": self.same_body,
            "malformed": self.malformed,
            "rejected": self.rejected,
            "absurd": self.absurd,
            "quarantined": self.quarantined,
            "held": self.held,
            "oversized": self.oversized,
            "rate_limited": self.rate_limited,
            "overflow": self.overflow,
            "dropped": self.dropped,
            "side_dropped": self.side_dropped,
            "published": self.published,
            "fuses": self.fuses,
            "full_fuses": self.full_fuses,
            "alignments": self.alignments,
            "malformed_by": dict(sorted(self.malformed_by.items())),
            "rejected_by": dict(sorted(self.rejected_by.items())),
            "absurd_by": dict(sorted(self.absurd_by.items())),
            "quarantined_by": dict(sorted(self.quarantined_by.items())),
            "side_dropped_by": dict(sorted(self.side_dropped_by.items())),
            "latency_ms": self.latencies_ms.summary(fresh_latency),
        }


def latency_summary(lat_ms: Iterable[float]) -> dict[str, float | int | None]:
    """``{n, p50, p99, max}`` of latencies in ms (None for each statistic when there are none)."""
    a = lat_ms if isinstance(lat_ms, np.ndarray) else np.asarray(list(lat_ms), dtype=np.float64)
    if len(a) == 0:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    p50, p99 = np.percentile(a, [50, 99])
    return {"n": len(a), "p50": float(p50), "p99": float(p99), "max": float(a.max())}
