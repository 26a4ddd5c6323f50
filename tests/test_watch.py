"""``wiremap watch`` (agents/commands/watch.py): in-process for the per-payload logic, then as a
real process against a real Zenoh router on 127.0.0.1."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.commands.watch import Watcher
from agents.fleet.bus import FleetKeys, free_port, tcp_endpoint
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from tests.fleet_util import client, in_process_router, log_text, spawn, stop_process, wait_until

KEYS = FleetKeys("default")
ROOM = [(0.0, 0.0), (6.0, 0.0), (6.0, 4.0), (0.0, 4.0)]
LINE = re.compile(r"^fused v(\d+): (\d+) vertices, (\d+) edges, ([\d,]+) bytes; (\d+) robots? alive", re.M)


def room(extra: int = 0) -> Wireframe:
    """A room, with ``extra`` more corners along its bottom wall (so versions differ)."""
    xs = np.linspace(0.0, 6.0, extra + 2)[1:-1]
    return Wireframe.from_polylines([[ROOM[0], *[(float(x), 0.0) for x in xs], *ROOM[1:]]])


def message(version: int, wf: Wireframe | None = None, kind: str = "FUSED_MAP", **meta: Any) -> bytes:
    from wire_codec import MapMessage, MessageKind, encode

    return encode(
        MapMessage(
            MessageKind[kind],
            "fusion" if kind == "FUSED_MAP" else "r1",
            version,
            1_000 + version,
            Pose(),
            "fleet",
            Pose(),
            0.05,
            room(version) if wf is None else wf,
            ("r1", "r2") if kind == "FUSED_MAP" else (),
            dict(meta),
        )
    )


class _Sample:
    def __init__(self, key: str, kind: Any) -> None:
        self.key_expr = key
        self.kind = kind


# ---------------------------------------------------------------------------- in process
def test_watcher_lines_duplicates_and_malformed(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import zenoh

    w = Watcher(KEYS, tmp_path / "out")
    w.liveliness(_Sample(KEYS.alive("r2"), zenoh.SampleKind.PUT))
    w.liveliness(_Sample(KEYS.alive("r1"), zenoh.SampleKind.PUT))
    w.liveliness(_Sample("wiremap/other/alive/r9", zenoh.SampleKind.PUT))  # another fleet: ignored
    data = message(3, stale=["r2"])
    line = w.handle(data)
    assert line == (  # r2's token is still here, but the fusion service says it is stale: not alive
        f"fused v3: 7 vertices, 7 edges, {len(data):,} bytes; 1 robot alive (r1); from r1 r2(stale)"
    )
    assert w.handle(data) is None  # the same version again (query answer + subscription)
    w.liveliness(_Sample(KEYS.alive("r2"), zenoh.SampleKind.DELETE))
    assert w.handle(message(4)) is not None and "1 robot alive (r1);" in capsys.readouterr().out
    assert w.handle(b"\x00\x01 not a message") is None
    assert w.handle(message(5, kind="ROBOT_MAP")) is None
    assert (w.shown, w.malformed) == (2, 2)
    err = capsys.readouterr().err
    assert "skipped a malformed payload (16 bytes)" in err and "skipped a robot_map message" in err
    w.flush(force=True)  # v4 came within a second of v3: saved at the next flush (or at exit)
    saved = sorted(p.name for p in (tmp_path / "out").iterdir())
    # bounded: latest.* always, a numbered copy at most every --save-every seconds (v3 only here)
    assert saved == ["fused-v3.geojson", "fused-v3.png", "latest.geojson", "latest.png"]
    latest = json.loads((tmp_path / "out" / "latest.geojson").read_text())
    assert latest["properties"]["version"] == 4 and latest["properties"]["robots_alive"] == ["r1"]
    assert Wireframe.from_geojson(latest).almost_equal(room(4), tol=1e-3)
    assert (tmp_path / "out" / "fused-v3.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------- real processes
def _versions(text: str) -> list[int]:
    return [int(m.group(1)) for m in LINE.finditer(text)]


@pytest.mark.fleet
def test_watch_process_query_subscription_and_save(tmp_path: Path) -> None:
    save = tmp_path / "maps"
    log = tmp_path / "watch.log"
    with in_process_router() as ep, client(ep) as s:
        tokens = [s.liveliness().declare_token(KEYS.alive(r)) for r in ("r1", "r2")]
        v1 = message(1)
        # The fusion service answers the start-up query with the current map.
        qbl = s.declare_queryable(KEYS.fused_map, lambda q: q.reply(KEYS.fused_map, v1), complete=True)
        p = spawn(["watch", "--connect", ep, "--count", "3", "--save", save, "--timeout", "30"], log)
        try:
            wait_until(lambda: "watching" in log_text(p, log) or p.poll() is not None, 30, "watch to start")
            wait_until(
                lambda: 1 in _versions(log_text(p, log)) or p.poll() is not None, 15, "v1 from the query"
            )
            s.put(KEYS.fused_map, b"\xde\xad\xbe\xef" * 8)  # malformed: counted and skipped
            s.put(KEYS.fused_map, message(9, kind="ROBOT_MAP"))  # not a fused map: skipped
            for v in (2, 2, 3):  # v2 twice: shown once
                s.put(KEYS.fused_map, message(v))
            rc = p.wait(timeout=30)
        finally:
            stop_process(p)
            qbl.undeclare()
            del tokens
    text = log.read_text()
    assert rc == 0, text
    assert _versions(text) == [1, 2, 3], text
    for m in LINE.finditer(text):
        v = int(m.group(1))
        wf = room(v)
        assert (int(m.group(2)), int(m.group(3))) == (wf.n_vertices, wf.n_edges)
        assert int(m.group(4).replace(",", "")) == len(message(v))
        assert int(m.group(5)) == 2, text
    assert "2 malformed payloads skipped" in text and "Traceback" not in text
    # the first version numbered, the others within --save-every (30 s): latest only
    assert sorted(p.name for p in save.iterdir()) == ["fused-v1.geojson", "fused-v1.png", "latest.geojson",
                                                      "latest.png"]
    doc = json.loads((save / "fused-v1.geojson").read_text())
    assert doc["properties"]["version"] == 1
    assert Wireframe.from_geojson(doc).almost_equal(room(1), tol=1e-3)
    assert (save / "latest.png").read_bytes()[:4] == b"\x89PNG"
    latest = json.loads((save / "latest.geojson").read_text())
    assert latest["properties"]["version"] == 3 and Wireframe.from_geojson(latest).almost_equal(
        room(3), tol=1e-3
    )


@pytest.mark.fleet
def test_watch_stops_on_sigterm_and_on_timeout(tmp_path: Path) -> None:
    with in_process_router() as ep:
        a = spawn(["watch", "--connect", ep], tmp_path / "a.log")
        b = spawn(["watch", "--connect", ep, "--count", "1", "--timeout", "2"], tmp_path / "b.log")
        try:
            wait_until(lambda: "watching" in log_text(a, tmp_path / "a.log"), 30, "watch to start")
            t0 = time.monotonic()
            rc_a = stop_process(a, signal.SIGTERM, timeout=10)
            took = time.monotonic() - t0
            rc_b = b.wait(timeout=30)
        finally:
            stop_process(a)
            stop_process(b)
    assert rc_a == 0 and took < 5.0, (rc_a, took)
    assert "0 versions shown, 0 malformed payloads skipped" in (tmp_path / "a.log").read_text()
    text_b = (tmp_path / "b.log").read_text()
    assert rc_b == 1 and "timed out after 2 s with 0 of 1 versions" in text_b, text_b


@pytest.mark.fleet
def test_watch_without_router_is_one_error_line(tmp_path: Path) -> None:
    import os
    import sys

    from tests.fleet_util import REPO

    ep = tcp_endpoint(free_port())
    p = subprocess.run(
        [sys.executable, "-m", "agents", "watch", "--connect", ep, "--timeout", "1"],
        cwd=REPO,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 2, p.stderr
    assert "no router after 1 s" in p.stderr and "Traceback" not in p.stderr
    assert p.stdout == ""


def test_health_line_shows_the_store_flag_and_quarantines() -> None:
    from agents.commands.watch import health_line

    assert health_line({}) == "store ok; quarantined 0"
    doc = {
        "store": {"ok": False, "enabled": True, "error": "No space left on device", "written_version": 41,
                  "behind": 7},
        "stats": {"quarantined": 3},
        "quarantine": {"r3": {"reason": "fleet_walls", "count": 3}, "bad": "junk"},
    }
    assert (
        health_line(doc)
        == "store FAILING (No space left on device; on disk v41, 7 behind); quarantined 3 (r3: fleet_walls x3)"  # noqa: E501
    )
    assert (
        health_line({"store": {"enabled": False}, "stats": {"quarantined": "x"}})
        == "store off; quarantined 0"
    )
