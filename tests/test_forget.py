"""``wiremap fleet forget ID``: the fusion service removes a robot with no trace on an admin
query, and the store records why."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agents.fleet.bus import FleetKeys
from agents.fleet.fusion import FusionState, encode_message
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from tests.fleet_util import Fleet, client, in_process_router, query_stats, wait_until
from wire_codec.message import MapMessage, MessageKind

pytestmark = pytest.mark.fleet


def square(rid: str, seq: int) -> bytes:
    pts = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    return encode_message(
        MapMessage(
            kind=MessageKind.ROBOT_MAP, sender=rid, seq=seq, stamp_ns=time.time_ns(), pose=Pose.identity(),
            frame=f"odom/{rid}", origin=Pose(1.0, 2.0, 0.0), resolution=0.05,
            wireframe=Wireframe.build(pts, edges), meta={"boot": time.time_ns() - 10**9, "t": 1.0, "step": 1},
        )
    )  # fmt: skip


def test_forget_removes_a_robot_and_the_store_says_why(tmp_path: Path) -> None:
    keys = FleetKeys("forget")
    store = tmp_path / "store"
    with in_process_router() as ep, Fleet(tmp_path) as fleet, client(ep) as s:
        fleet.start("fuse",
                    ["fuse", "--connect", ep, "--fleet", keys.fleet, "--store", store,
                     "--save-interval", "0"])
        fleet.wait_log("fuse", "fusion service ready", 30)
        for rid in ("r1", "r2"):
            s.put(keys.robot_map(rid), square(rid, 1))
        wait_until(lambda: set((query_stats(s, keys) or {}).get("robots", {})) == {"r1", "r2"}, 20,
                   "both robots fused")
        out = subprocess.run(
            [sys.executable, "-m", "agents", "fleet", "forget", "r2", "--connect", ep, "--fleet", keys.fleet],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert out.returncode == 0, out.stderr
        assert "forgot r2 (its map removed)" in out.stdout
        doc = wait_until(lambda: (d := query_stats(s, keys)) and "r2" not in d["robots"] and d, 20,
                         "r2 forgotten")
        assert doc["fused"]["robots"] == ["r1"]
        assert "admin" in doc["forgotten"]["r2"]
        bad = subprocess.run(
            [sys.executable, "-m", "agents", "fleet", "forget", "no/such", "--connect", ep, "--fleet",
             keys.fleet],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert bad.returncode != 0 and "no robot id" in bad.stderr
        assert fleet.stop("fuse", timeout=20) == 0, fleet.log("fuse")
    st = FusionState.load(store)
    assert set(st.robots) == {"r1"} and "admin" in st.forgotten["r2"]
    assert not (store / "robots" / "r2.wfm").exists()
