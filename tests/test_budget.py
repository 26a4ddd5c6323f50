"""The per-robot work budget (agents/fleet/fusion/budget.py): a robot whose maps have cost its
share of fusion CPU has its next map held, the latest one only, until its bucket refills; the
other robots are not held."""

from __future__ import annotations

import time

from agents.fleet.fusion import FusionConfig, FusionState
from agents.fleet.fusion.budget import BudgetConfig, WorkBudget
from agents.sim.world import load_world
from mapping.se2 import Pose
from tests.test_quarantine import BOOT, S, part, raw_map


def test_bucket_refills_at_its_share() -> None:
    b = WorkBudget(BudgetConfig(share=0.5, burst_s=1.0))
    assert b.allowed("r1", 0.0)
    b.charge("r1", 1.5, 0.0)  # a fuse that cost more than the bucket held
    assert not b.allowed("r1", 0.5) and not b.allowed("r1", 1.0)
    assert b.allowed("r1", 1.01) and b.allowed("r2", 0.0)
    assert b.spent == {"r1": 1.5}


def test_a_robot_over_its_budget_waits_and_the_others_do_not() -> None:
    truth = load_world("museum").truth
    st = FusionState(FusionConfig(threshold=0.4, refine=False))
    st.budget = WorkBudget(BudgetConfig(share=1e-9, burst_s=1.0))
    t = BOOT + 100 * S
    assert st.offer(raw_map("r1", part(truth, (50.0, 50.0), 40.0), Pose(50.0, 50.0, 0.0), 1), "r1", t)
    assert st.offer(raw_map("r2", part(truth, (100.0, 100.0), 40.0), Pose(100.0, 100.0, 0.0), 1), "r2", t)
    st.fuse()
    st.budget.charge("r1", 5.0, time.monotonic())  # r1's maps have been expensive
    assert not st.offer(raw_map("r1", part(truth, (50.0, 50.0), 45.0), Pose(50.0, 50.0, 0.0), 2), "r1", t + S)
    assert not st.offer(raw_map("r1", part(truth, (50.0, 50.0), 50.0), Pose(50.0, 50.0, 0.0), 3),
                        "r1", t + 2 * S)
    assert st.stats.held == 2 and set(st.held) == {"r1"} and st.held["r1"][0].seq == 3
    assert st.offer(raw_map("r2", part(truth, (100.0, 100.0), 45.0), Pose(100.0, 100.0, 0.0), 2), "r2", t + S)
    assert st.release_held(t + 3 * S) == []
    st.budget = WorkBudget(BudgetConfig())  # refilled
    assert st.release_held(t + 3 * S) == ["r1"]
    assert st.robots["r1"].key[1] == 3 and not st.held
