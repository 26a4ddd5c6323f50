"""What a regional fuser's standby costs (``python -m tests.standby_cost [--robots 64] [--rate 10]
[--seconds 20]``): one regional fuser over the first half of the fleet (``range::rK``), once with
its standby (the default: it keeps the latest bytes of every other robot's map) and once with
``--no-standby``, the same robot traffic (synthetic maps ``r01..``, each re-sent at ``--rate``
per second, half of them in the fuser's group). Prints the fuser's CPU share in each case and
the payload bytes per second that reach it. A development measurement (figures in
``docs/experiments.md``), not one of ``wiremap bench``'s benchmarks.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any


def _run(standby: bool, n: int, rate: float, seconds: float, work: Path) -> dict[str, Any]:
    from agents.bench.common import Procs
    from agents.fleet.bus import FleetKeys, build_config, free_port, open_session, tcp_endpoint
    from agents.fleet.fusion import encode_message
    from agents.fleet.proc import cpu_seconds
    from tests.tree_util import robot_views

    ep = tcp_endpoint(free_port())
    keys = FleetKeys("standby")
    msgs = robot_views("museum", n, seed=1)
    raws = [(keys.robot_map(m.sender), encode_message(m)) for m in msgs]
    half = sorted(m.sender for m in msgs)[n // 2]
    router = open_session(build_config("router", None, (), [ep]), wait=False)
    assert router is not None
    try:
        with Procs(work / ("standby" if standby else "no-standby")) as procs:
            argv = ["-m", "agents", "fuse", "--connect", ep, "--fleet", "standby", "--group", "g0",
                    "--robots", f"range::{half}", "--no-refine", *([] if standby else ["--no-standby"])]
            p = procs.start("g0", argv)
            procs.wait_log("g0", "ready", 60.0)
            pub = open_session(build_config("client", None, [ep]))
            assert pub is not None
            try:
                tokens = [pub.liveliness().declare_token(keys.alive(m.sender)) for m in msgs]
                got = {"bytes": 0}
                def count(smp: Any) -> None:
                    got["bytes"] += len(smp.payload)

                sub = router.declare_subscriber(f"{keys.prefix}/robots/*/map", count)
                for key, raw in raws:  # a first round: every map accepted once
                    pub.put(key, raw)
                time.sleep(2.0)
                c0, t0, b0 = cpu_seconds(p.pid) or 0.0, time.monotonic(), got["bytes"]
                period = 1.0 / rate
                nxt = t0
                while time.monotonic() - t0 < seconds:
                    for key, raw in raws:  # heartbeats: the same content (decoded, not re-fused)
                        pub.put(key, raw)
                    nxt += period
                    time.sleep(max(0.0, nxt - time.monotonic()))
                wall = time.monotonic() - t0
                c1 = cpu_seconds(p.pid) or 0.0
                sub.undeclare()
                for t in tokens:
                    t.undeclare()
            finally:
                pub.close()
            return {"standby": standby, "robots": n, "rate_hz": rate,
                    "cpu_share": round((c1 - c0) / wall, 4),
                    "maps_per_s_to_fuser": round(n * rate, 1),
                    "bytes_per_s_published": round((got["bytes"] - b0) / wall)}
    finally:
        router.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.standby_cost", description=__doc__)
    ap.add_argument("--robots", type=int, default=64)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--seconds", type=float, default=20.0)
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="wiremap-standby-") as d:
        rows = [_run(s, a.robots, a.rate, a.seconds, Path(d)) for s in (False, True, False, True)]
    for r in rows:
        print(json.dumps(r), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
