"""A store that cannot lie: after every corruption the service resumes the same map (and a
version that never goes backwards) or refuses to start; nothing is lost silently."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import msgpack
import pytest

from agents.fleet.fusion import SNAPSHOT, FusionConfig, FusionState, StoreDamaged, StoreWriter, read_store
from agents.fleet.fusion.store import SNAPSHOT_MAGIC, seal_snapshot, unseal_snapshot
from tests.test_bad_input import ROOM, robot_msg

CFG = FusionConfig(refine=False)


def saved(tmp_path: Path) -> tuple[Path, FusionState]:
    st_ = FusionState(CFG)
    st_.add(robot_msg("r1"))
    st_.add(robot_msg("r2", wf=ROOM.transformed(robot_msg().origin.compose(robot_msg().origin))))
    st_.fuse()
    st_.add(robot_msg("r1", seq=2))
    st_.fuse()
    d = tmp_path / "s"
    st_.save(d)
    return d, st_


def rewrite_snapshot(d: Path, **changes: object) -> None:
    body = msgpack.unpackb(unseal_snapshot((d / SNAPSHOT).read_bytes()), raw=False)
    body.update(changes)
    (d / SNAPSHOT).write_bytes(seal_snapshot(msgpack.packb(body, use_bin_type=True)))


def same_as(back: FusionState, st_: FusionState) -> None:
    assert set(back.robots) == set(st_.robots)
    assert back.fused.almost_equal(st_.fused, tol=1e-9)
    assert back.version >= st_.version


def test_snapshot_is_sealed_and_a_flipped_byte_is_caught(tmp_path: Path) -> None:
    d, st_ = saved(tmp_path)
    data = bytearray((d / SNAPSHOT).read_bytes())
    assert data.startswith(SNAPSHOT_MAGIC)
    data[-10] ^= 0x01
    (d / SNAPSHOT).write_bytes(bytes(data))
    c = read_store(d)
    assert not c.from_snapshot and any("damaged" in x for x in c.damaged)
    same_as(FusionState.load(d, CFG), st_)  # recovered from the views and state.json


@pytest.mark.parametrize("version", [2**64 - 1, -5, 1e300, "x"])
def test_absurd_snapshot_version_is_recovered_from_the_other_files(tmp_path: Path, version: object) -> None:
    d, st_ = saved(tmp_path)
    rewrite_snapshot(d, version=version)
    back = FusionState.load(d, CFG)
    same_as(back, st_)
    assert back.version == st_.version


@pytest.mark.parametrize("alignment", [[1e300, 0.0, 0.0], [100_000.0, 0.0, 0.0], [float("nan"), 0, 0], "x"])
def test_absurd_alignment_is_never_served(tmp_path: Path, alignment: object) -> None:
    d, st_ = saved(tmp_path)
    rewrite_snapshot(d, alignments={"r1": None, "r2": alignment})
    back = FusionState.load(d, CFG)
    assert all(abs(c.x) < 10 for c in back.corrections.values())
    same_as(back, st_)


def test_a_corrupt_view_is_recovered_and_written_again(tmp_path: Path) -> None:
    d, st_ = saved(tmp_path)
    (d / "robots" / "r2.wfm").write_bytes(b"\x00" * 40)
    back = FusionState.load(d, CFG)
    same_as(back, st_)
    assert back.store_rewrite == {"r2"}
    back.save(d, sorted(back.store_rewrite))
    assert (d / "robots" / "r2.wfm").read_bytes() == st_.robots["r2"].raw


def test_every_file_unreadable_refuses_to_start_or_resets_forward(tmp_path: Path) -> None:
    d, st_ = saved(tmp_path)
    for f in [d / SNAPSHOT, d / "state.json", d / "fused.wfm", *(d / "robots").iterdir()]:
        f.write_bytes(b"garbage")
    with pytest.raises(StoreDamaged):
        FusionState.load(d, CFG)
    back = FusionState.load(d, CFG, reset=True)
    assert not back.robots and back.version > st_.version  # never backwards for a subscriber
    aside = [p for p in d.iterdir() if p.name.startswith("damaged-")]
    assert len(aside) == 1 and (aside[0] / SNAPSHOT).read_bytes() == b"garbage"  # nothing deleted


def test_snapshot_damaged_and_a_recorded_view_lost_refuses(tmp_path: Path) -> None:
    d, _ = saved(tmp_path)
    (d / SNAPSHOT).write_bytes(b"garbage")
    (d / "robots" / "r2.wfm").unlink()
    with pytest.raises(StoreDamaged, match="r2"):
        FusionState.load(d, CFG)


def test_state_json_is_checksummed(tmp_path: Path) -> None:
    d, st_ = saved(tmp_path)
    doc = json.loads((d / "state.json").read_text())
    doc["version"] = 10**30
    (d / "state.json").write_text(json.dumps(doc))
    c = read_store(d)
    assert c.version == st_.version and any("state.json" in x for x in c.damaged)


def test_a_stored_map_from_the_future_is_refused_and_reported(tmp_path: Path) -> None:
    from agents.fleet.fusion import encode_message

    d, st_ = saved(tmp_path)
    future = encode_message(robot_msg("r3", meta={"boot": 10**19 // 2, "t": 1.0}))
    rewrite_snapshot(d, robots={**{r: e.raw for r, e in st_.robots.items()}, "r3": future})
    back = FusionState.load(d, CFG, now_ns=10**18)
    assert "r3" not in back.robots and any("r3" in x and "future" in x for x in back.store_report)


@pytest.mark.fleet  # runs wiremap fuse as a process
def test_fuse_refuses_a_damaged_store_in_one_line(tmp_path: Path) -> None:
    d, _ = saved(tmp_path)
    for f in [d / SNAPSHOT, d / "state.json", d / "fused.wfm"]:
        f.write_bytes(b"garbage")
    r = subprocess.run(
        [sys.executable, "-m", "agents.cli", "fuse", "--store", str(d), "--connect", "tcp/127.0.0.1:1"],
        capture_output=True, text=True, timeout=60,
    )
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and "--reset" in r.stderr


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_a_read_only_store_is_a_health_flag(tmp_path: Path) -> None:
    d, st_ = saved(tmp_path)
    os.chmod(d, 0o500)
    try:
        w = StoreWriter()
        w.submit(st_.store_job(d))
        w.flush(10)
        assert not w.ok and w.errors == 1 and w.last_error
        w.close()
    finally:
        os.chmod(d, 0o700)


def test_a_failing_disk_is_a_health_flag(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from agents.fleet.fusion import store

    d, st_ = saved(tmp_path)

    def full(*_a: object, **_k: object) -> None:
        raise OSError(28, "No space left on device")

    w = StoreWriter()
    monkeypatch.setattr(store, "write_atomic", full)
    w.submit(st_.store_job(d))
    w.flush(10)
    assert not w.ok and "No space" in w.last_error
    monkeypatch.undo()
    st_.version += 1
    w.submit(st_.store_job(d))
    w.flush(10)
    assert w.ok and w.written_version == st_.version
    w.close()

