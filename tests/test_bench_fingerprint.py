"""``wiremap bench fingerprint``: the same seed hashes the same, and a change is located."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from agents.bench.fingerprint import compare, fingerprint
from agents.cli import main
from agents.sim.world import load_world


def test_same_seed_same_hashes_and_a_difference_is_located() -> None:
    world = load_world("paper-small")
    a = fingerprint(world, 1, 60)
    b = fingerprint(world, 1, 60)
    assert a["poses"] == b["poses"] and a["checkpoints"] == b["checkpoints"] and a["best"] == b["best"]
    assert compare(a, b) == "IDENTICAL"
    other = fingerprint(world, 2, 60)
    assert compare(other, a).startswith("DIFFERENT")
    moved = copy.deepcopy(a)
    moved["pose_blocks"] = ["0" * 16]
    a_long = copy.deepcopy(a)
    a_long["pose_blocks"] = ["f" * 16]
    assert compare(moved, a_long) == "DIFFERENT: poses differ within steps 1-500"


def test_against_an_earlier_run_exits_1_on_a_difference(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "fingerprint", "--world", "paper-small", "--seeds", "1", "--steps", "40", "--json",
                 "--quiet"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    before = tmp_path / "before.txt"
    before.write_text(line + "\n")
    assert main(["bench", "fingerprint", "--world", "paper-small", "--seeds", "1", "--steps", "40", "--quiet",
                 "--against", str(before)]) == 0
    assert "IDENTICAL" in capsys.readouterr().out
    doc = json.loads(line)
    doc["runs"]["paper-small:0"]["poses"] = "0" * 16
    before.write_text(json.dumps(doc) + "\n")
    assert main(["bench", "fingerprint", "--world", "paper-small", "--seeds", "1", "--steps", "40", "--quiet",
                 "--against", str(before)]) == 1
    assert main(["bench", "fingerprint", "--world", "paper-small", "--against", str(tmp_path / "nope")]) == 2
