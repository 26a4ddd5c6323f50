"""One stolen robot must not take the fleet down: `wiremap run --secure` with three robots,
and an attacker holding r3's own credentials (while r3 runs) sending every attack of the
issue on r3's keys. The supervisor (which hosts the router) and the fusion service stay up,
the honest robots keep merging, the fused map stays precise, every attack is counted under
its reason in ``fused/stats``."""

from __future__ import annotations

import json
import re
import shutil
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from agents.fleet.bus import FleetKeys, encode_pose
from agents.fleet.fusion import encode_message
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from tests.fleet_util import Fleet, client, query_stats, wait_until
from wire_codec.message import MapMessage, MessageKind

pytestmark = [
    pytest.mark.fleet,
    pytest.mark.skipif(shutil.which("openssl") is None,
                       reason="the openssl command generates the test certificates"),
]


def junk_map(n: int, span: float, boot: int, seq: int, rng: np.random.Generator, origin: Pose) -> bytes:
    pts = rng.uniform(-span, span, size=(n, 2))
    edges = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    return encode_message(
        MapMessage(
            kind=MessageKind.ROBOT_MAP, sender="r3", seq=seq, stamp_ns=time.time_ns(), pose=Pose.identity(),
            frame="odom/r3", origin=origin, resolution=0.05, wireframe=Wireframe.build(pts, edges),
            meta={"boot": boot, "t": 1.0, "step": 1},
        )
    )  # fmt: skip


def attacks(doc: dict[str, Any]) -> list[tuple[str, bytes]]:
    """(key suffix, payload) of every attack; ``doc`` is the fused/stats the attacker can read."""
    rng = np.random.default_rng(7)
    now = time.time_ns()
    real = doc["robots"]["r3"]
    boot, seq = int(real["boot"]), int(real["seq"])
    origin = Pose(1.0, 1.0, 0.0)
    good_pose = msgpack.unpackb(encode_pose(seq=1, t=1.0, stamp_ns=now, odom=origin, fleet=origin), raw=False)
    out: list[tuple[str, bytes]] = [
        ("pose", msgpack.packb({**good_pose, "t": 1e300})),  # crash 1: Rerun's set_time
        ("pose", msgpack.packb({**good_pose, "status": {"step": "x"}})),  # crash 2: run's progress line
        ("pose", msgpack.packb({**good_pose, "fleet": [float("nan"), 0, 0]})),
        ("viz",
         msgpack.packb({"t": float("inf"), "pose": [0, 0, 0], "scan": {}, "particles": [], "weights": []})),
        ("map", junk_map(5000, 900.0, now, seq + 1, rng, origin)),  # over the vertex budget
        ("map", junk_map(1500, 900.0, boot, seq + 1, rng, origin)),  # kilometres of junk walls
        ("map", junk_map(3, 600.0, boot, seq + 1, rng, origin)),  # walls beyond the robot's reach
        ("map", junk_map(20, 5.0, now + 3600 * 10**9, 1, rng, origin)),  # lockout: a boot from the future
        ("map", junk_map(20, 5.0, now - 10**9, 1, rng, origin)),  # a boot without a restart
        ("map", junk_map(20, 5.0, boot, seq + 10**9, rng, origin)),  # lockout: a seq far ahead
    ]
    return out


ABSURD_KINDS = {"budget_walls", "reach", "future", "seq_jump"}


SIDE_KINDS = ("pose_time", "pose_not_finite", "viz_not_finite")


def _every_attack_counted(st: dict) -> bool:
    """Each absurd kind, the restart claim, the oversized map and each bad pose or scan counted
    at least once (the maps and the side channel are counted on their own paths)."""
    side = st.get("side_dropped_by", {})
    return (ABSURD_KINDS <= set(st.get("absurd_by", {}))
            and st.get("rejected_by", {}).get("boot_without_restart", 0) >= 1
            and st.get("malformed", 0) >= 1
            and all(side.get(k, 0) for k in SIDE_KINDS))


def test_one_stolen_robot_does_not_take_the_fleet_down(tmp_path: Path) -> None:
    out = tmp_path / "out"
    keys = FleetKeys()
    with Fleet(tmp_path) as fleet:
        # 20 s of mapping: the routes take about 11 s at 10 Hz; the attacks are counted about 8 s
        # into the mapping (r3 in the fused map, 3 rounds of 10 attacks 0.2 s apart)
        p = fleet.start(
            "run",
            ["run", "--secure", "--world", "paper-small", "--robots", "3", "--duration", "20", "--rate", "10",
             "--particles", "3", "--out", out],
        )  # fmt: skip
        text = fleet.wait_log("run", "router on", 60)
        m = re.search(r"router on (tls/localhost:\d+)", text)
        assert m, text
        ep = m.group(1)
        creds = out / "secure" / "credentials"
        with client(ep, timeout=30, credentials=creds / "r3.json") as thief, client(
            ep, timeout=30, credentials=creds / "monitor.json"
        ) as mon:
            doc = wait_until(lambda: (d := query_stats(thief, keys)) and "r3" in d["robots"] and d, 90,
                             "r3 in the fused map")  # fmt: skip
            before = doc["version"]
            for _ in range(3):
                for kind, payload in attacks(doc):
                    key = {"pose": keys.robot_pose, "viz": keys.robot_viz, "map": keys.robot_map}[kind]("r3")
                    thief.put(key, payload)
                    time.sleep(0.2)  # poses and scans: only the latest per robot is looked at
            # the honest robots keep merging: new versions keep coming
            wait_until(lambda: (d := query_stats(mon, keys)) and d["version"] > before + 3, 30,
                       "new versions")
            # Every kind of attack counted: when the fusion drains two of a round's maps in one
            # batch, only the newest on r3's key is decoded and the other counts as superseded,
            # so under load fewer than the 12 absurd maps sent are judged (4 kinds x 3 rounds).
            st = wait_until(lambda: (d := query_stats(mon, keys)) and _every_attack_counted(d["stats"]) and d,
                            20, "the attacks counted")["stats"]  # fmt: skip
        assert p.wait(timeout=120) == 0, fleet.log("run")
    # The 5,000-vertex maps, refused by the decoder's budget: one per round, on r3's own key, so
    # when the fusion drains a round's maps in one batch only the newest is decoded and the
    # others count as superseded (never decoded, never fused); under load that took some.
    assert st["malformed"] >= 1, st
    print(json.dumps(st, indent=1))
    assert ABSURD_KINDS <= set(st["absurd_by"]), st
    by = st["side_dropped_by"]
    assert all(by.get(k, 0) for k in SIDE_KINDS), st
    # every round sends a map claiming a restart r3's session never made; at least one is
    # counted under that reason (a round's may be stopped first by another guard: the count
    # was 2 of 3 in some runs, and why is not yet traced)
    assert st["rejected_by"].get("boot_without_restart", 0) >= 1, st
    for log in [tmp_path / "run.log", *(out / "logs").glob("*.log")]:
        assert "Traceback" not in log.read_text(), log
    rep = json.loads((out / "report.json").read_text())
    assert rep["fused"]["robots"] == ["r1", "r2", "r3"]
    assert rep["fused"]["wall_precision"] >= 0.95, rep["fused"]
    assert rep["fused"]["vertices"] < 400, rep["fused"]
