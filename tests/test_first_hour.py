"""What a newcomer meets in the first hour, each case pinned so that it does not come back:
the live block fits the terminal, outputs are checked before any work, interruptions write
what there is, one GeoJSON schema, one size for the fused map, readable warnings and help.

Numbers in the comments are the items of the first-hour review (see the commit messages).
"""

from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.cli import main as cli_main
from tests.fleet_util import REPO

ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _status(step: int, finished: bool = False) -> dict[str, Any]:
    return {"step": step, "t": step * 0.5, "vertices": 33, "edges": 27, "maps_sent": step,
            "bytes_sent": 14_398 * step, "finished": finished}


# ---------------------------------------------------------------------------- 1. the live block
@pytest.mark.parametrize("columns", [80, 60, 40])
def test_run_progress_fits_the_terminal(monkeypatch: pytest.MonkeyPatch, columns: int) -> None:
    from agents.commands import run as run_cmd

    monkeypatch.setattr(run_cmd, "terminal_width", lambda stream=None: columns)
    monkeypatch.setattr(run_cmd, "terminal_rows", lambda stream=None: 30)
    term = FakeTerminal()
    p = run_cmd.Progress(["r1", "r2", "r10"], enabled=True, stream=term)
    p.set_fused(b"x" * 196, 116, 42, 42, ["r1", "r2", "r10"])
    for k, rid in enumerate(p.ids):
        p.status[rid] = _status(90 + k, finished=k == 0)
    p.draw(18.9, 60, force=True)
    p.draw(19.0, 60, force=True)
    text = term.getvalue()
    # the second draw moves up exactly the lines of the first, each line is cleared first
    first, second = text.split("\x1b[5F")
    assert first.count("\n") == 5 and second.count("\n") == 5
    for line in ANSI.sub("", text).splitlines():
        assert len(line) <= columns - 1, (columns, line)  # the last column free: nothing wraps
    if columns == 80:  # nothing cut at 80 columns, and the header sits over its columns
        lines = ANSI.sub("", second).splitlines()
        assert "196 bytes" in lines[0] and lines[2].endswith("done")
        head, row = lines[1], lines[2]
        for title in ("steps", "corners", "walls", "maps", "sent"):
            end = head.index(title) + len(title)
            assert row[end - 1] != " ", (title, head, row)  # right-aligned under its title


def test_run_progress_with_more_robots_than_rows(monkeypatch: pytest.MonkeyPatch) -> None:
    from agents.commands import run as run_cmd

    monkeypatch.setattr(run_cmd, "terminal_width", lambda stream=None: 80)
    monkeypatch.setattr(run_cmd, "terminal_rows", lambda stream=None: 10)
    term = FakeTerminal()
    p = run_cmd.Progress([f"r{k}" for k in range(1, 17)], enabled=True, stream=term)
    p.draw(1.0, 60, force=True)
    lines = ANSI.sub("", term.getvalue()).splitlines()
    assert len(lines) <= 9 and "more robots" in lines[-1]


def test_run_progress_not_a_terminal_prints_plain_lines() -> None:
    from agents.commands.run import Progress

    out = io.StringIO()
    p = Progress(["r1"], enabled=True, stream=out)
    p.draw(1.0, 60, force=True)
    assert "\x1b" not in out.getvalue() and out.getvalue().count("\n") == 3


def test_run_progress_of_a_log_counts_from_its_first_stamp() -> None:
    """A CARMEN fleet (open-ended, the log's stamps in Unix time, as belgioioso's are): the clock
    line shows the seconds run, not "of 1e+09 s", and a robot's time counts from the log's first
    scan; the report's ``sim_time_s`` the same way."""
    from agents.commands.run import OPEN_ENDED, Progress, status_figures

    out = io.StringIO()
    p = Progress(["r1", "r2"], enabled=True, stream=out, t0=1_018_929_000.0)
    p.status["r1"] = {**_status(12), "t": 1_018_929_650.5}
    p.draw(16.6, OPEN_ENDED, force=True)
    head, _, r1, r2 = out.getvalue().splitlines()
    assert head.startswith("[ 16.6 s] ") and "e+" not in head
    assert " 650.5 s " in r1 and "1018929" not in r1
    assert r2.split() == ["r2", "waiting"]
    assert status_figures({"t": 1_018_929_650.5}, 1_018_929_000.0)["sim_time_s"] == 650.5
    assert status_figures({}, 1_018_929_000.0)["sim_time_s"] == 0.0


def test_map_progress_fits_and_ends_its_line(monkeypatch: pytest.MonkeyPatch) -> None:
    from agents.commands import map_cmd
    from agents.commands import run as run_cmd

    monkeypatch.setattr(run_cmd, "terminal_width", lambda stream=None: 30)
    term = FakeTerminal()
    p = map_cmd.Progress(True, term)
    p.update(1234, 5000, 281, 300, 142.5, force=True)
    p.close()
    text = term.getvalue()
    assert text.endswith("\n")
    assert all(len(ANSI.sub("", s)) <= 29 for s in text.replace("\r", "\n").splitlines())


# ---------------------------------------------------------------------------- 2. the demo stops
def test_make_demo_stops_when_done_with_duration_as_the_cap() -> None:
    make = (REPO / "Makefile").read_text()
    demo = make.split("\ndemo:")[1].split("\n\n")[0]
    assert "--stop-when-done" in demo and "--duration" in demo


# ---------------------------------------------------------------------------- 4, 13. checked before any work
@pytest.fixture()
def afile(tmp_path: Path) -> Path:
    f = tmp_path / "afile"
    f.write_text("I am a file")
    return f


CASES = {
    "map --out": ["map", "--world", "paper-small", "--out", "{f}/sub"],
    "run --out": ["run", "--world", "paper-small", "--robots", "2", "--out", "{f}/sub"],
    "run --particles 0": ["run", "--world", "paper-small", "--robots", "2", "--particles", "0",
                          "--out", "{d}/run"],
    "world --png": ["world", "show", "paper-small", "--png", "{f}/x.png"],
    "world --geojson": ["world", "show", "paper-small", "--geojson", "{f}/x.geojson"],
    "world --svg": ["world", "show", "paper-small", "--svg", "{f}/deeper/x.svg"],
    "export --out": ["export", "{d}/m.geojson", "--out", "{f}/x.geojson"],
    "export rosmap": ["export", "{d}/m.geojson", "--format", "rosmap", "--out", "{f}/map"],
    "watch --save": ["watch", "--connect", "tcp/127.0.0.1:9", "--save", "{f}/w"],
    "fuse --store": ["fuse", "--connect", "tcp/127.0.0.1:9", "--store", "{f}/s"],
    "fuse --rrd": ["fuse", "--connect", "tcp/127.0.0.1:9", "--rrd", "{f}/x.rrd"],
    "robot --status-file": ["robot", "--id", "r1", "--world", "paper-small", "--start", "2,2",
                            "--connect", "tcp/127.0.0.1:9", "--status-file", "{f}/x.json"],
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_unwritable_output_is_one_line_before_any_work(
    case: str, afile: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    from mapping.wireframe import Wireframe

    (tmp_path / "m.geojson").write_text(json.dumps(Wireframe.from_polylines([[(0, 0), (1, 0)]]).to_geojson()))
    argv = [a.format(f=afile, d=tmp_path) for a in CASES[case]]
    t0 = time.monotonic()
    try:
        rc = cli_main(argv)
    except SystemExit as exc:
        rc = int(exc.code or 0)
    took = time.monotonic() - t0
    err = capfd.readouterr().err
    assert rc == 2, (case, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "afile" in err or "--particles" in err, err
    assert took < 10, f"{case}: {took:.1f} s before the error"  # no mapping, no fleet first
    assert not (tmp_path / "run").exists()  # nothing started, nothing made


# ---------------------------------------------------------------------------- 5. Ctrl-C on map
@pytest.mark.fleet
@pytest.mark.parametrize("second", [None, 0.0, 0.2], ids=["once", "twice", "twice-later"])
def test_map_ctrl_c_writes_what_there_is(tmp_path: Path, second: float | None) -> None:
    """Ctrl-C once, or again once the scans have stopped (at once, or 0.2 s later: while the map
    is written, or as the command exits): the map as it stands, whole, and exit 130."""
    out = tmp_path / "m"
    env = {"PYTHONUNBUFFERED": "1", "PATH": "/usr/bin:/bin"}
    p = subprocess.Popen(
        [sys.executable, "-m", "agents", "map", "--world", "office", "--particles", "2", "--out", str(out)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True,
        # Ctrl-C as a terminal delivers it: a suite started in the background of a
        # non-interactive shell (CI, `make test &`) passes SIGINT on ignored, and Python then
        # installs no KeyboardInterrupt handler (the map ran to its end: a flake under load)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        assert p.stderr is not None
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60:  # the first progress line: mapping has begun
            line = p.stderr.readline()
            if line.startswith("step ") or not line:
                break
        time.sleep(0.5)
        p.send_signal(signal.SIGINT)
        seen = ""
        if second is not None:  # once the scans have stopped: while the outputs are written
            while "interrupted after" not in seen and (line := p.stderr.readline()):
                seen += line
            time.sleep(second)
            p.send_signal(signal.SIGINT)
        stdout, stderr = p.communicate(timeout=60)
        stderr = seen + stderr
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130, stderr
    assert "Traceback" not in stderr
    assert re.search(r"^wiremap map: interrupted after \d+ steps", stderr, re.M), stderr  # its own line
    for name in ("map.geojson", "map.png", "trajectory.tsv", "report.json"):
        assert (out / name).is_file(), name
    rep = json.loads((out / "report.json").read_text())
    assert rep["interrupted"] is True and rep["metrics"]["cell_error"] is None
    assert "interrupted" in stdout


def test_ctrl_c_is_a_flag_during_the_drive_and_a_second_one_raises_until_writing() -> None:
    from agents.commands.map_cmd import _CtrlC

    # Python's own handler, as in a terminal (a suite run in the background inherits SIGINT ignored)
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with _CtrlC() as ctrl_c:
            assert signal.getsignal(signal.SIGINT) is not signal.default_int_handler
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # the handler runs at the next bytecode: a flag, no exception
            assert ctrl_c.hit
            with pytest.raises(KeyboardInterrupt):
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(1.0)
            ctrl_c.writing = True  # the outputs are being written: noted, never raised
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    finally:
        signal.signal(signal.SIGINT, outer)


# ---------------------------------------------------------------------------- 6. robot start pose
class _Agent:
    from agents.fleet.robot import RobotAgent

    _check_start = RobotAgent._check_start

    def __init__(self, start: str) -> None:
        import argparse

        from agents.commands.robot import add_arguments, options_from_args

        ap = argparse.ArgumentParser()
        add_arguments(ap)
        self.opts = options_from_args(ap.parse_args(["--id", "r1", "--world", "paper-small",
                                                     "--start", start]))
        self.said: list[str] = []
        self._last_body = None

    def say(self, text: str) -> None:
        self.said.append(text)


def test_robot_start_heading_is_the_routes_and_warnings_are_readable() -> None:
    from mapping.se2 import Pose

    true_start = Pose(2.0, 2.0, np.pi / 2)
    quiet = _Agent("2,2")
    quiet._check_start(true_start)
    assert quiet.said == [] and quiet.opts.start == true_start
    told = _Agent("2,2,0")
    told._check_start(true_start)
    assert told.said == [
        "start heading 0 deg replaced by 90 deg (a simulated robot starts facing along its route)"
    ]
    moved = _Agent("2.5,2,0")
    moved._check_start(true_start)
    assert re.fullmatch(r"--start 2\.50,2\.00 differs from .*"
                        r"\(2\.00,2\.00, heading 90 deg\); using the latter",
                        moved.said[0])


def test_robot_help_says_who_chooses_the_heading(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli_main(["robot", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "facing along its route" in text and "simulated seconds" in text and "--router-timeout" in text


# ---------------------------------------------------------------------------- 7. per-robot cell error
def test_partial_maps_have_no_cell_error_and_summaries_round() -> None:
    from agents.commands.run import _metrics
    from agents.sim.world import load_world

    truth = load_world("paper-small").truth
    part = truth.subgraph_edges(np.arange(truth.n_edges) < 10)
    m = _metrics(truth, part, 0.2, partial=True)
    assert m["cell_error"] is None and "unexplored" in m["cell_error_note"]
    assert m["wall_precision"] == pytest.approx(1.0)
    assert _metrics(truth, truth, 0.2)["cell_error"] == 0.0


# ---------------------------------------------------------------------------- 9, 11. one size, one schema
def _fused(seq: int, stale: list[str]) -> bytes:
    from agents.sim.world import load_world
    from mapping.se2 import Pose
    from wire_codec import MapMessage, MessageKind, encode

    wf = load_world("paper-small").truth
    wf = wf.replace(sources=np.where(np.arange(wf.n_edges) % 2 == 0, 1, 3).astype(np.uint64))
    return encode(MapMessage(MessageKind.FUSED_MAP, "fusion", seq, 1_700_000_000_000_000_000, Pose(), "fleet",
                             Pose(), 0.05, wf, robots=("r1", "r2"),
                             meta={"version": seq, "threshold": 0.2, "stale": stale, "t": 12.5}))


def test_run_outputs_one_size_and_the_export_schema(tmp_path: Path) -> None:
    from agents.commands.run import write_outputs
    from agents.sim.world import load_world

    out = tmp_path / "run"
    (out / "store").mkdir(parents=True)
    (out / "store" / "fused.wfm").write_bytes(_fused(7, []))  # the store: no live metadata
    published = _fused(7, ["r2"])  # the bus: the same version with its stale list
    world = load_world("paper-small")
    rep = write_outputs(out, world, ["r1", "r2"], 10.0, {"robot_status": {}}, published=published,
                        tracks={"r1": np.array([[2.0, 2.0], [3.0, 2.5]])})
    assert (out / "fused.wfm").read_bytes() == published and rep["fused"]["bytes"] == len(published)
    assert rep["per_robot"]["r1"]["cell_error"] is None
    assert cli_main(["export", str(out / "fused.wfm"), "--out", str(tmp_path / "e.geojson")]) == 0
    ran = json.loads((out / "fused.geojson").read_text())
    exported = json.loads((tmp_path / "e.geojson").read_text())
    assert set(ran["properties"]) - {"world"} == set(exported["properties"])
    for key in ("kind", "version", "merge_threshold", "robots", "stale", "resolution"):
        assert ran["properties"][key] == exported["properties"][key], key
    walls = [f["properties"] for f in exported["features"] if f["properties"]["kind"] == "wall"]
    assert {tuple(w["robots"]) for w in walls} == {("r1",), ("r1", "r2")}
    assert ran["features"] == exported["features"]


# ---------------------------------------------------------------------------- 12. a second run
def test_a_new_run_clears_the_previous_runs_files(tmp_path: Path) -> None:
    from agents.commands.run import clear_previous_run

    out = tmp_path / "demo"
    for rel in ("logs/r4.log", "status/r4.json", "routes/r4.json", "store/robots/r4.wfm", "secure/ca.pem",
                "fused.png", "report.json"):
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text("old")
    (out / "my-notes.txt").write_text("mine")
    clear_previous_run(out)
    assert sorted(p.name for p in out.iterdir()) == ["my-notes.txt"]


# ---------------------------------------------------------------------------- 14. a robot without router
@pytest.mark.fleet
def test_robot_without_router_says_what_it_tries_and_times_out(tmp_path: Path) -> None:
    from agents.fleet.bus import free_port

    ep = f"tcp/127.0.0.1:{free_port()}"
    p = subprocess.run(
        [sys.executable, "-m", "agents", "robot", "--id", "r1", "--world", "paper-small", "--start", "2,2",
         "--connect", ep, "--router-timeout", "1"],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )
    assert p.returncode == 2, p.stderr
    assert "waiting for a router" in p.stdout and ep in p.stdout
    assert "no router after 1 s" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.fleet
def test_open_session_repeats_its_waiting_report(monkeypatch: pytest.MonkeyPatch) -> None:
    from agents.errors import UserError
    from agents.fleet import bus

    monkeypatch.setattr(bus, "WAIT_REPORT_S", 0.2)
    said: list[str] = []
    cfg = bus.build_config("client", connect=[f"tcp/127.0.0.1:{bus.free_port()}"])
    with pytest.raises(UserError, match="no router after"):
        bus.open_session(cfg, timeout=0.9, on_wait=said.append)
    assert len(said) >= 3 and "s so far" in said[-1]


# ---------------------------------------------------------------------------- 15. pictures
def test_figure_has_title_legend_truth_and_shading() -> None:
    from agents.files.render import FIGURE_TRUTH_COLOR, OUTSIDE_COLOR, decode_png, map_figure
    from agents.sim.world import load_world

    w = load_world("paper-small")
    half = w.truth.subgraph_edges(np.arange(w.truth.n_edges) % 2 == 0)
    img = decode_png(map_figure(half, w.truth, title="a title", trajectories={"r1": [(2, 2), (5, 2)]},
                                free=w.free_space, max_px=600))
    assert img.shape[0] > 600 + 80  # title strip and legend rows around the map
    assert (img[5:30, 10:100] < 128).any()  # the title's text
    assert (img[-90:, :] < 128).any()  # legend text and the scale bar
    colours = {tuple(c) for c in img.reshape(-1, 3)[:: 7].tolist()}
    assert OUTSIDE_COLOR in colours and FIGURE_TRUTH_COLOR in colours


# ---------------------------------------------------------------------------- 17. help and numbers
@pytest.mark.parametrize(
    ("argv", "present", "absent"),
    [
        (["bench", "--help"], ["sensor"], []),
        # every benchmark is named (hostile, slam and fingerprint were missing)
        (["--help"], ["soak, hostile, sensor", "slam, scanners, live, fingerprint"], []),
        (["config", "show", "--help"], ["FilterConfig"], ["``", ":class:"]),
        (["world", "show", "--help"], ["examples:"], ["``"]),
        (["replay", "--help"], ["core", "recording.rrd"], ["--record"]),
        (["run", "--help"], ["wall-clock", "2.5x", "upper bound"], []),
        (["map", "--help"], ["simulated seconds"], []),
    ],
)
def test_help_texts(
    argv: list[str], present: list[str], absent: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        cli_main(argv)
    text = " ".join(capsys.readouterr().out.split())
    for word in present:
        assert word in text, (argv, word)
    for word in absent:
        assert word not in text, (argv, word)


def test_rosmap_yaml_numbers_are_short() -> None:
    from agents.files.export import OccupancyGrid, map_yaml

    grid = OccupancyGrid(np.zeros((2, 2), np.uint8), 0.05, (-0.17500000000000002, 0.1 + 0.2))
    text = map_yaml(grid, "map.pgm")
    assert "origin: [-0.175, 0.3, 0.0]" in text


# ---------------------------------------------------------------------------- 16. the recording
def test_recording_has_one_fleet_clock_trajectories_events_and_alive_series(tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    from agents.files.rerun_log import FleetRecorder
    from mapping.se2 import Pose

    rec = FleetRecorder(tmp_path / "r.rrd")
    for k in range(5):  # r1 drives from sim time 0
        rec.log_robot_pose("r1", 0.5 * k, Pose(1.0 + 0.2 * k, 1.0, 0.0), None)
    time.sleep(1.1)
    for k in range(5):  # r2 joins later, its own simulated clock from 0 again
        rec.log_robot_pose("r2", 0.5 * k, Pose(5.0, 1.0 + 0.2 * k, 0.0), None)
        rec.log_robot_pose("r1", 2.5 + 0.5 * k, Pose(2.0 + 0.2 * k, 1.0, 0.0), None)
    rec.log_robot_status("r1", 5.0, stale=True)
    rec.close()
    first: dict[str, int] = {}
    rows: dict[str, int] = {}
    texts: list[str] = []
    for c in RrdReader(str(tmp_path / "r.rrd")).stream().to_chunks():
        b = c.to_record_batch()
        p = str(c.entity_path)
        rows[p] = rows.get(p, 0) + b.num_rows
        if "fleet_time" in b.schema.names and b.num_rows:
            col = b.column("fleet_time")
            t = min(int(v) for v in col.cast("int64").to_pylist() if v is not None)
            first[p] = min(first.get(p, t), t)
        if p == "/log":
            texts += [str(v) for v in b.column("TextLog:text").to_pylist()]
    assert first["/robots/r2/pose"] - first["/robots/r1/pose"] >= 1_000_000_000  # r2 appears a second later
    assert rows["/robots/r1/trajectory"] >= 2 and rows["/stats/robots/r1/alive"] >= 2
    assert any("r2 joined" in t for t in texts) and any("r1 stale" in t for t in texts)
