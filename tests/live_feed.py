"""A development measurement (not a test): a CARMEN log fed to a live ``wiremap robot`` over a
real router on loopback, as ROS 2 CDR messages at SPEED times the log's own pace; prints the
robot's final map precision against the log's real scan endpoints (the map placed at the truth's
first pose), its live counters and its ms per step, as one JSON line.

``python -m tests.live_feed LOG SPEED`` (from the repository's folder).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import zenoh

from agents.commands.play import live_times
from agents.files.carmen import read_carmen_log, scan_truth
from agents.fleet.bus import FleetKeys, decode_pose, free_port
from agents.fleet.carmen_fleet import endpoint_precision, endpoints
from tests.test_live_lidar import messages
from wire_codec import decode


def main() -> None:
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    log_path, speed = sys.argv[1], float(sys.argv[2])
    log = read_carmen_log(log_path)
    scans = live_times(list(log.scans), 10.0)  # times a live robot can pair, as wiremap play gives them
    truth = scan_truth(log)
    if truth is None:
        raise SystemExit(f"{log_path}: no truth")
    out = Path(tempfile.mkdtemp(prefix="live-feed-"))
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen([sys.executable, "-m", "agents", "router", "--listen", ep],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(1.5)
    robot = subprocess.Popen(
        [sys.executable, "-m", "agents", "robot", "--id", "lv", "--scan-key", "l/scan",
         "--odom-key", "l/odom", "--connect", ep, "--fleet", "lf", "--particles", "10", "--seed", "1",
         "--status-file", str(out / "status.json")],
        stdout=open(out / "robot.log", "w"), stderr=subprocess.STDOUT)
    keys = FleetKeys("lf")
    latest: dict[str, Any] = {}
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([ep]))
    session = zenoh.open(cfg)
    subs = []
    try:
        subs = [
            session.declare_subscriber(keys.robot_map("lv"),
                                       lambda x: latest.__setitem__("map", decode(x.payload.to_bytes()))),
            session.declare_subscriber(keys.robot_pose("lv"),
                                       lambda x: latest.__setitem__("st", decode_pose(x.payload.to_bytes()))),
        ]
        time.sleep(8)  # the robot's start-up (numba's kernels)
        t0, k = time.monotonic(), 0
        for kind, data in messages(scans):
            if kind == "scan":  # each scan at its time in the log, SPEED times faster
                while time.monotonic() < t0 + (scans[k].t - scans[0].t) / speed:
                    time.sleep(0.002)
                k += 1
            session.put(f"l/{kind}", data, congestion_control=zenoh.CongestionControl.BLOCK)
        fed = time.monotonic() - t0
        time.sleep(8)  # what is queued is mapped
        robot.send_signal(signal.SIGINT)
        robot.wait(30)
        status = json.loads((out / "status.json").read_text())
        wf = latest["map"].wireframe.transformed(truth[0])
        print(json.dumps({
            "log": Path(log_path).name, "speed": speed, "scans": len(scans), "steps": status["step"],
            "live": {k: v for k, v in status["live"].items() if k != "last_issue"},
            "precision_as_placed": round(endpoint_precision(wf, endpoints(scans, truth)), 3),
            "step_ms": status["step_ms"], "feed_s": round(fed, 1),
        }))
    finally:
        for sub in subs:
            sub.undeclare()
        session.close()
        if robot.poll() is None:
            robot.kill()
        router.terminate()
        router.wait()


if __name__ == "__main__":
    main()
