"""Bad flags, missing files, bad worlds and bad poses: every ``wiremap`` subcommand answers with
one clear line on stderr and a non-zero exit, never a traceback.

The cases run in this process through :func:`agents.cli.main` (file-descriptor level capture, so
anything Zenoh or a library writes to stderr counts too); a few also run as real processes to
cover the ``python -m agents`` entry point. None of them needs a router: every one fails before
it would wait for one.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from agents.cli import main
from agents.commands.replay import RRD_MAGIC
from agents.fleet.bus import free_port
from tests.fleet_util import REPO


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    d = tmp_path_factory.mktemp("cli")
    garbage = d / "garbage.wfm"
    garbage.write_bytes(b"\x00\x01 not a map")
    bad_json = d / "bad.json"
    bad_json.write_text("{not json")
    bad_world = d / "world.geojson"
    bad_world.write_text('{"type": "FeatureCollection", "features": [{"type": "Feature"}]}')
    bad_cfg = d / "bad.json5"
    bad_cfg.write_text("{mode: ")
    open_creds = d / "open.json"
    open_creds.write_text('{"user": "r1", "password": "x"}')
    open_creds.chmod(0o644)
    a_file = d / "a-file"
    a_file.write_text("x")
    garbage_bag = d / "garbage.bag"
    garbage_bag.write_bytes(b"#ROSBAG V2.0\n\x00\x01 cut short")
    rrd = d / "head-only.rrd"  # passes the magic-bytes check, so the next check is reached
    rrd.write_bytes(RRD_MAGIC + b"\x00" * 16)
    return {
        "dir": str(d),
        "missing": str(d / "missing.file"),
        "garbage": str(garbage),
        "bad_json": str(bad_json),
        "bad_world": str(bad_world),
        "bad_cfg": str(bad_cfg),
        "open_creds": str(open_creds),
        "a_file": str(a_file),
        "garbage_bag": str(garbage_bag),
        "rrd": str(rrd),
        "log": str(REPO / "tests" / "data" / "freiburg-101-head.log.gz"),
    }


ROBOT = ["robot", "--id", "r1", "--world", "paper-small"]
CASES: dict[str, list[str]] = {
    # every subcommand: an unknown flag
    **{f"{c}-bad-flag": [c, "--no-such-flag"] for c in
       ("map", "worlds", "world", "run", "robot", "play", "fuse", "router", "watch", "replay", "export",
        "bench")},
    "no-command-flag": ["--no-such-flag"],
    "unknown-command": ["frobnicate"],
    # map
    "map-bad-world": ["map", "--world", "no-such-world", "--out", "{dir}/m"],
    "map-world-file-missing": ["map", "--world", "{missing}", "--out", "{dir}/m"],
    "map-world-file-bad": ["map", "--world", "{bad_world}", "--out", "{dir}/m"],
    "map-carmen-missing": ["map", "--carmen", "{missing}", "--out", "{dir}/m"],
    "map-rosbag-missing": ["map", "--rosbag", "{missing}", "--out", "{dir}/m"],
    "map-rosbag-garbage": ["map", "--rosbag", "{garbage_bag}", "--out", "{dir}/m"],
    "map-rosbag-not-a-bag": ["map", "--rosbag", "{garbage}", "--out", "{dir}/m"],
    "map-rosbag-and-carmen": ["map", "--rosbag", "{missing}", "--carmen", "{missing}", "--out", "{dir}/m"],
    "map-bad-particles": ["map", "--world", "paper-small", "--out", "{dir}/m", "--particles", "0"],
    "map-no-out": ["map", "--world", "paper-small"],
    # world / worlds
    "world-bad-world": ["world", "show", "no-such-world"],
    "world-file-bad": ["world", "show", "{bad_json}"],
    "world-bad-robots": ["world", "show", "paper-small", "--plan", "--robots", "0"],
    # run
    "run-bad-world": ["run", "--world", "no-such-world", "--robots", "2", "--out", "{dir}/r"],
    "run-bad-robots": ["run", "--world", "paper-small", "--robots", "0", "--out", "{dir}/r"],
    "run-bad-duration": ["run", "--world", "paper-small", "--robots", "1", "--duration", "-3",
                         "--out", "{dir}/r"],
    "run-bad-config": ["run", "--world", "paper-small", "--robots", "1", "--out", "{dir}/r", "--config",
                       "{bad_cfg}"],
    "run-missing-config": ["run", "--world", "paper-small", "--robots", "1", "--out", "{dir}/r", "--config",
                           "{missing}"],
    "run-bad-listen": ["run", "--world", "paper-small", "--robots", "1", "--out", "{dir}/r", "--listen",
                       "nonsense"],
    "run-missing-credentials": ["run", "--world", "paper-small", "--robots", "1", "--out", "{dir}/r",
                                "--credentials", "{missing}"],
    "run-secure-with-listen": ["run", "--secure", "--world", "paper-small", "--robots", "1",
                               "--out", "{dir}/r", "--listen", "tls/localhost:7447"],
    "run-bad-fleet": ["run", "--world", "paper-small", "--robots", "1", "--out", "{dir}/r", "--fleet", "a/b"],
    "run-out-is-a-file": ["run", "--world", "paper-small", "--robots", "1", "--out", "{a_file}"],
    "run-rosbag-missing": ["run", "--rosbag", "{missing}", "--robots", "2", "--out", "{dir}/r"],
    "run-rosbag-garbage": ["run", "--rosbag", "{garbage_bag}", "--robots", "2", "--out", "{dir}/r"],
    "run-rosbag-and-carmen": ["run", "--rosbag", "{garbage_bag}", "--carmen", "{log}", "--robots", "2",
                              "--out", "{dir}/r"],
    "run-topic-without-rosbag": ["run", "--carmen", "{log}", "--scan-topic", "/scan", "--robots", "2",
                                 "--out", "{dir}/r"],
    # robot
    "robot-bad-world": ["robot", "--id", "r1", "--world", "no-such-world", "--start", "2,2,0"],
    "robot-rosbag-missing": ["robot", "--id", "r1", "--rosbag", "{missing}"],
    "robot-rosbag-and-carmen": ["robot", "--id", "r1", "--rosbag", "{garbage_bag}", "--carmen", "{log}"],
    "robot-topic-without-rosbag": ["robot", "--id", "r1", "--carmen", "{log}", "--odom-topic", "/odom"],
    "robot-live-without-odom": ["robot", "--id", "r1", "--scan-key", "scan"],
    "robot-bad-pose": [*ROBOT, "--start", "2"],
    "robot-bad-pose-numbers": [*ROBOT, "--start", "a,b,c"],
    "robot-nan-pose": [*ROBOT, "--start", "nan,1,0"],
    "robot-no-pose": ROBOT,
    "robot-bad-id": ["robot", "--id", "r 1", "--world", "paper-small", "--start", "2,2,0"],
    "robot-bad-route": [*ROBOT, "--route", "1,2;x"],
    "robot-route-missing": [*ROBOT, "--route", "{missing}.json"],
    "robot-route-bad-json": [*ROBOT, "--route", "{bad_json}"],
    "robot-bad-rate": [*ROBOT, "--start", "2,2,0", "--rate", "0"],
    "robot-missing-credentials": [*ROBOT, "--start", "2,2,0", "--credentials", "{missing}"],
    "robot-bad-credentials": [*ROBOT, "--start", "2,2,0", "--credentials", "{bad_json}"],
    "robot-open-credentials": [*ROBOT, "--start", "2,2,0", "--credentials", "{open_creds}"],
    "robot-bad-config": [*ROBOT, "--start", "2,2,0", "--config", "{bad_cfg}"],
    "robot-bad-connect": [*ROBOT, "--start", "2,2,0", "--connect", "nonsense"],
    "robot-bad-fleet": [*ROBOT, "--start", "2,2,0", "--fleet", "x*"],
    "robot-outside-world": [*ROBOT, "--start", "500,500,0"],
    # fuse
    "fuse-store-is-a-file": ["fuse", "--store", "{a_file}"],
    "fuse-bad-threshold": ["fuse", "--threshold", "-1"],
    "fuse-bad-rate-limit": ["fuse", "--rate-limit", "0"],
    "fuse-root-bad-min-interval": ["fuse", "--of-groups", "g0,g1", "--min-interval", "-1"],
    "bench-fleet-bad-fuse-interval": ["bench", "fleet", "--fuse-interval", "nan"],
    "fuse-viewer-without-rrd": ["fuse", "--serve-viewer", "9999"],
    "fuse-missing-credentials": ["fuse", "--credentials", "{missing}"],
    "fuse-missing-config": ["fuse", "--config", "{missing}"],
    "fuse-bad-connect": ["fuse", "--connect", "nonsense"],
    # router
    "router-missing-config": ["router", "--config", "{missing}"],
    "router-bad-config": ["router", "--config", "{bad_cfg}"],
    "router-bad-listen": ["router", "--listen", "nonsense"],
    "router-port-in-use": ["router", "--listen", "tcp/127.0.0.1:{busy}"],
    # watch, replay, export, bench
    "watch-missing-config": ["watch", "--config", "{missing}"],
    "watch-missing-credentials": ["watch", "--credentials", "{missing}"],
    "watch-bad-count": ["watch", "--count", "0"],
    "replay-missing": ["replay", "{missing}.rrd"],
    "replay-not-a-recording": ["replay", "{garbage}"],
    "export-missing": ["export", "{missing}.wfm", "--out", "{dir}/e.svg"],
    "export-garbage": ["export", "{garbage}", "--out", "{dir}/e.svg"],
    "export-bad-format": ["export", "{garbage}", "--out", "{dir}/e.svg", "--format", "bmp"],
    "bench-unknown": ["bench", "no-such-bench"],
    "bench-accuracy-bad-world": ["bench", "accuracy", "--world", "no-such-world", "--seeds", "1"],
    "bench-register-negative-large": ["bench", "register", "--quick", "--large", "-1"],
    # found by a first-hour review: each used to run, crash with a traceback or be ignored
    "run-empty-out": ["run", "--world", "paper-small", "--robots", "1", "--out", ""],
    "map-empty-out": ["map", "--world", "paper-small", "--out", ""],
    "map-out-in-proc": ["map", "--world", "paper-small", "--out", "/proc/wiremap-test"],
    "world-png-in-proc": ["world", "show", "paper-small", "--png", "/proc/wiremap-test/w.png"],
    "world-tiny-png": ["world", "show", "paper-small", "--png", "{dir}/w.png", "--max-px", "0"],
    "bench-out-under-a-file": ["bench", "accuracy", "--world", "paper-small", "--seeds", "1", "--steps", "2",
                               "--out", "{a_file}/sub"],
    "bench-accuracy-zero-steps": ["bench", "accuracy", "--world", "paper-small", "--seeds", "1",
                                  "--steps", "0"],
    "bench-hostile-negative-messages": ["bench", "hostile", "--no-fleet", "--messages", "-1"],
    "robot-zero-duration": [*ROBOT, "--start", "2,2,0", "--duration", "0"],
    "robot-negative-viz-rate": [*ROBOT, "--start", "2,2,0", "--viz-rate", "-1"],
    "robot-unknown-world-no-pose": ["robot", "--id", "r1", "--world", "no-such-world"],
    "map-negative-seed": ["map", "--world", "paper-small", "--seed", "-1", "--out", "{dir}/m"],
    "map-carmen-duration": ["map", "--carmen", "{log}", "--duration", "1", "--out", "{dir}/m"],
    "map-world-strict": ["map", "--world", "paper-small", "--strict", "--out", "{dir}/m"],
    "map-world-lidar-profile": ["map", "--world", "paper-small", "--lidar-profile", "lidar",
                                "--out", "{dir}/m"],
    "run-zero-fusers": ["run", "--world", "paper-small", "--robots", "2", "--fusers", "0",
                        "--out", "{dir}/r"],
    "run-more-fusers-than-robots": ["run", "--world", "paper-small", "--robots", "2", "--fusers", "5",
                                    "--out", "{dir}/r"],
    "replay-bad-bind": ["replay", "{rrd}", "--web", "--bind", "999.1.1.1"],
    "run-world-lidar-profile": ["run", "--world", "paper-small", "--robots", "1", "--lidar-profile", "lidar",
                                "--out", "{dir}/r"],
    "bench-lidar-zero-steps": ["bench", "lidar", "--data", "{dir}", "--steps", "0"],
}  # fmt: skip


@pytest.fixture(scope="module")
def busy_port() -> object:
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", free_port()))
    s.listen(1)
    yield s.getsockname()[1]
    s.close()


def _argv(case: str, files: dict[str, str], busy: int) -> list[str]:
    return [a.format(**files, busy=busy) for a in CASES[case]]


# router-port-in-use opens a Zenoh router (which then fails to listen): fleet lane.
@pytest.mark.parametrize("case", [pytest.param(c, marks=pytest.mark.fleet) if c == "router-port-in-use" else c
                                  for c in sorted(CASES)])
def test_one_line_error_and_nonzero_exit(
    case: str, files: dict[str, str], busy_port: int, capfd: pytest.CaptureFixture[str]
) -> None:
    argv = _argv(case, files, busy_port)
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse
        rc = exc.code if isinstance(exc.code, int) else 1
    out, err = capfd.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc != 0, (argv, out, err)
    assert len(lines) == 1, (argv, err)
    assert "Traceback" not in err and "Traceback" not in out
    assert lines[0].startswith("wiremap"), lines[0]


# Cases that would wait for a router if the check came too late: run only as processes, with a
# time limit (an in-process hang would hang the test run).
BEFORE_THE_BUS: dict[str, list[str]] = {
    "fuse-bad-world": ["fuse", "--world", "no-such-world", "--connect", "tcp/127.0.0.1:{closed}"],
    "fuse-store-under-a-file": ["fuse", "--store", "{a_file}/store", "--connect", "tcp/127.0.0.1:{closed}"],
    "fuse-rrd-under-a-file": ["fuse", "--rrd", "{a_file}/x.rrd", "--connect", "tcp/127.0.0.1:{closed}"],
    "robot-status-under-a-file": [*ROBOT, "--start", "2,2,0", "--status-file", "{a_file}/s.json",
                                  "--connect", "tcp/127.0.0.1:{closed}"],
}  # fmt: skip


@pytest.mark.fleet
@pytest.mark.parametrize("case",
                         ["robot-bad-pose", "fuse-store-is-a-file", "export-garbage", "run-bad-world",
                          *BEFORE_THE_BUS])
def test_real_processes_too(case: str, files: dict[str, str], busy_port: int) -> None:
    argv = CASES.get(case) or BEFORE_THE_BUS[case]
    r = subprocess.run(
        [sys.executable, "-m", "agents",
         *[a.format(**files, busy=busy_port, closed=free_port()) for a in argv]],
        capture_output=True, text=True, cwd=REPO, timeout=60,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert len([ln for ln in r.stderr.splitlines() if ln.strip()]) == 1, r.stderr
    assert "Traceback" not in r.stderr + r.stdout
