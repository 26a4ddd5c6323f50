"""``wiremap replay FILE.rrd`` (agents/commands/replay.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from agents.cli import main as cli_main
from agents.commands import replay as R
from tests.fleet_util import REPO, log_text, spawn, stop_process, wait_until


def make_rrd(path: Path) -> Path:
    import rerun as rr

    rec = rr.RecordingStream("wiremap-test", recording_id="replay-test")
    rec.save(str(path))
    rec.set_time("step", sequence=0)
    rec.log("map/corners", rr.Points2D([[0.0, 0.0], [1.0, 0.0]]))
    rec.flush(timeout_sec=5)
    return path


@pytest.fixture(scope="module")
def rrd(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_rrd(tmp_path_factory.mktemp("rrd") / "run.rrd")


def replay(*args: str) -> int:
    try:
        return int(cli_main(["replay", *args]))
    except SystemExit as exc:
        return int(exc.code or 0)


def test_rrd_fixture_has_the_magic(rrd: Path) -> None:
    assert rrd.read_bytes()[:3] == R.RRD_MAGIC
    assert R.check_recording(rrd) == rrd


def test_no_display_is_exit_2_with_advice(
    rrd: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    started: list[object] = []
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: started.append(a))  # must not run
    assert replay(str(rrd)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("wiremap replay: no display")
    assert f"wiremap replay {rrd} --web" in err and f"rerun rrd stats {rrd}" in err
    assert started == []


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        (None, "no such file"),
        (b"PK\x03\x04 a zip, not a recording", "not a Rerun recording"),
        ("dir", "is a directory"),
    ],
)
def test_bad_file_is_exit_2(
    tmp_path: Path, content: bytes | str | None, needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "x.rrd"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content == "dir":
        path.mkdir()
    assert replay(str(path)) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1


def test_has_display_rules() -> None:
    assert not R.has_display({}, "linux")
    assert not R.has_display({"DISPLAY": ""}, "linux")
    assert R.has_display({"DISPLAY": ":0"}, "linux")
    assert R.has_display({"WAYLAND_DISPLAY": "wayland-0"}, "linux")
    assert R.has_display({}, "darwin") and R.has_display({}, "win32")
    assert not R.has_display({}, "freebsd14")


def test_viewer_command_and_rerun_lookup(rrd: Path) -> None:
    assert R.viewer_command("/x/rerun", rrd, web=False) == ["/x/rerun", str(rrd)]
    web = R.viewer_command("/x/rerun", rrd, web=True, bind="127.0.0.1", port=0)
    assert web[:2] == ["/x/rerun", "--serve-web"] and web[-1] == str(rrd)
    assert web[web.index("--bind") + 1] == "127.0.0.1" and web[web.index("--web-viewer-port") + 1] == "0"
    found = R.find_rerun()
    assert found is not None and Path(found).name == "rerun" and os.access(found, os.X_OK)
    # The native binary, not the Python wrapper script (a signal to the wrapper orphans it).
    assert Path(found).read_bytes()[:4] == b"\x7fELF" or sys.platform != "linux"


@pytest.mark.fleet
def test_subprocess_no_display_and_missing_file(rrd: Path, tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = str(REPO)
    for target, needle in ((rrd, "no display"), (tmp_path / "missing.rrd", "no such file")):
        p = subprocess.run(
            [sys.executable, "-m", "agents", "replay", str(target)],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert p.returncode == 2, p.stderr
        assert needle in p.stderr and "Traceback" not in p.stderr
        assert len(p.stderr.strip().splitlines()) == 1


@pytest.mark.fleet
def test_web_viewer_serves_and_stops_on_sigterm(rrd: Path, tmp_path: Path) -> None:
    log = tmp_path / "web.log"
    p = spawn(["replay", str(rrd), "--web", "--port", "0"], log)
    try:
        wait_until(
            lambda: "Hosting a web-viewer at http://127.0.0.1:" in log_text(p, log) or p.poll() is not None,
            30,
            "the web viewer",
        )
        assert p.poll() is None, log_text(p, log)
        rc = stop_process(p, signal.SIGTERM, timeout=10)
    finally:
        stop_process(p)
    assert rc == 0, log_text(p, log)
    assert "Traceback" not in log.read_text()
    # The viewer went with it: nothing still serves this recording.
    ps = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True, check=True).stdout
    assert not any("--serve-web" in line and str(rrd) in line for line in ps.splitlines()), ps
