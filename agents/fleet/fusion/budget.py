"""A work budget per robot: CPU seconds of fusion a robot's maps may cost per second.

Each robot has a token bucket of CPU seconds (``share`` refilled per second, ``burst_s`` deep).
The fusion state charges it what the robot's maps cost: the consistency checks of its maps, the
fuses that took a new map of it (shared between the robots whose maps they took), its ICP
alignments. A robot whose bucket is empty has its next maps *held* (the latest one only)
until the bucket has refilled; its last fused map stays in the fused map meanwhile. So a robot
sending maps that are expensive to fuse gets them fused less often, and the fusion loop keeps
serving the others. Honest robots cost a few milliseconds per map (``share`` is 20 % of a core
per robot; a 16-robot fleet at 10 maps/s each uses about one core for everything).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BudgetConfig:
    """share : CPU seconds per second a robot's maps may cost. burst_s : the bucket's depth."""

    share: float = 0.2
    burst_s: float = 1.0


class WorkBudget:
    """The per-robot buckets (times are the caller's clock in seconds)."""

    def __init__(self, config: BudgetConfig | None = None) -> None:
        self.config = config or BudgetConfig()
        self._buckets: dict[str, tuple[float, float]] = {}  # robot -> (seconds left, when)
        self.spent: dict[str, float] = {}  # robot -> CPU seconds charged in all

    def _level(self, rid: str, now: float) -> float:
        cfg = self.config
        left, at = self._buckets.get(rid, (cfg.burst_s, now))
        return min(cfg.burst_s, left + cfg.share * max(0.0, now - at))

    def allowed(self, rid: str, now: float) -> bool:
        """Whether the robot's bucket is not empty."""
        return self._level(rid, now) > 0.0

    def charge(self, rid: str, seconds: float, now: float) -> None:
        """Take ``seconds`` of CPU from the robot's bucket (it may go negative: a fuse that
        cost more than the bucket held is paid back before the robot's next map)."""
        self._buckets[rid] = (self._level(rid, now) - seconds, now)
        self.spent[rid] = self.spent.get(rid, 0.0) + seconds

    def forget(self, rid: str) -> None:
        self._buckets.pop(rid, None)
        self.spent.pop(rid, None)
