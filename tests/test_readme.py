"""The README's Usage, walked: every shell line of its ``sh`` blocks runs in a fresh temporary
folder, after the Quick start's ``make demo`` (the Makefile's own demo line, faster), and none
may fail or print a traceback.

Substitutions (and only these) keep it short and independent of the machine: free ports for
7447 and the web viewer's, shorter runs (``--rate 20``, ``--duration 3``, ``--steps 100``), a
small CARMEN log written from the simulator for ``intel.log`` (none ships with the repository)
and a ROS 1 bag of the same scans for ``lab.bag``,
and the web viewer stopped with Ctrl-C as soon as it answers on its port (it must, within 30 s).
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

from agents.fleet.bus import free_port
from tests.fleet_util import REPO


def usage_lines(readme: str) -> list[str]:
    """The shell lines of the README's ``## Usage`` section, in order (comment lines dropped)."""
    section = readme.split("\n## Usage\n", 1)[1].split("\n## ", 1)[0]
    lines: list[str] = []
    for block in re.findall(r"```sh\n(.*?)```", section, re.S):
        lines += [ln for ln in block.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    return lines


def demo_line(makefile: str) -> str:
    """The Makefile's ``make demo`` command with ``$(BIN)`` spelled out."""
    recipe = makefile.split("\ndemo:", 1)[1].split("\n\n", 1)[0]
    line = next(ln.strip() for ln in recipe.splitlines() if "wiremap" in ln)
    return line.replace("$(BIN)/", ".venv/bin/")


def test_usage_lines_are_what_the_walk_runs() -> None:
    lines = usage_lines((REPO / "README.md").read_text())
    assert lines[0] == "source .venv/bin/activate"
    commands = {ln.split()[1] for ln in lines if ln.startswith("wiremap ")}
    assert {"worlds", "world", "map", "run", "export", "replay", "router", "fuse", "robot",
            "watch"} <= commands
    assert any(ln.startswith("python -m wire_codec ") for ln in lines)


@pytest.mark.fleet
@pytest.mark.slow
def test_readme_usage_runs_pasted_into_a_shell(tmp_path: Path) -> None:
    import math

    from agents.files.carmen import read_carmen, write_carmen
    from tests.rosbag_util import write_scans_bag
    from tests.test_carmen import LidarConfig, simulated_scans

    (tmp_path / ".venv").symlink_to(REPO / ".venv")
    cfg = LidarConfig(beams=181, fov=math.pi, max_range=6.0, sigma=0.01)
    write_carmen(tmp_path / "intel.log", simulated_scans(cfg), fov=math.pi, max_range=cfg.max_range)
    write_scans_bag(tmp_path / "lab.bag", "ros1", read_carmen(tmp_path / "intel.log"))
    port, web = free_port(), free_port()
    subs = [
        ("7447", str(port)),
        ("--stop-when-done --seed 1", "--stop-when-done --seed 1 --rate 20"),
        ("--duration 30", "--duration 3 --rate 20"),
        ("--out out/small", "--out out/small --steps 100"),
        # serve, wait until the viewer's port answers (bash's /dev/tcp), Ctrl-C, and its status
        ("wiremap replay out/demo/recording.rrd --web",
         f"(wiremap replay out/demo/recording.rrd --web --port {web} & pid=$!; up=no; "
         f"for _ in $(seq 300); do if (exec 3<>/dev/tcp/127.0.0.1/{web}) 2>/dev/null; then up=yes; break; "
         f"fi; sleep 0.1; done; kill -INT $pid; wait $pid; test $up = yes)"),
    ]
    lines = [demo_line((REPO / "Makefile").read_text()), *usage_lines((REPO / "README.md").read_text())]
    script = []
    for ln in lines:
        for a, b in subs:
            ln = ln.replace(a, b)
        script.append(ln)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    env.update(RERUN_ANALYTICS="0", PYTHONUNBUFFERED="1")
    env.pop("DISPLAY", None)
    p = subprocess.run(
        ["bash", "-c", "PS4='+ $SECONDS s: '\nset -ex\n" + "\n".join(script)],
        cwd=tmp_path, capture_output=True, text=True, timeout=180, env=env,
    )
    text = p.stdout + p.stderr
    assert p.returncode == 0, text[-4000:]
    assert "Traceback" not in text, text[-4000:]
    for name in ("museum.png", "office.geojson", "out/small/map.png", "out/office/fused.png",
                 "out/intel/map.geojson", "out/lab/map.geojson", "out/demo/fused.pgm",
                 "out/demo/fused-export.png", "fused.geojson", "out/hand/watch/latest.png"):
        assert (tmp_path / name).is_file(), (name, text[-3000:])
