"""``python -m wire_codec`` and ``wiremap bench codec``."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

import wire_codec
from agents.bench import codec as bench
from mapping.wireframe import Wireframe
from tests.test_codec_util import room
from wire_codec.__main__ import main

ROOT = Path(__file__).resolve().parents[1]


def _geojson(tmp_path: Path, wf: Wireframe, name: str = "map.geojson") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(wf.to_geojson()))
    return path


def test_encode_decode_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = _geojson(tmp_path, room())
    out = tmp_path / "map.wfm"
    assert main(["encode", str(src), "--resolution", "0.1", "--sender", "r7", "--stamp-ns", "5", "-o",
                 str(out)]) == 0
    back = tmp_path / "back.geojson"
    assert main(["decode", str(out), "--geojson", str(back)]) == 0
    line = capsys.readouterr().out.strip()
    assert line == f"kind=robot_map sender=r7 version=1 seq=0 vertices=10 edges=10 bytes={out.stat().st_size}"
    doc = json.loads(back.read_text())
    assert doc["properties"]["resolution"] == 0.1 and doc["properties"]["frame"] == "odom/r7"
    assert Wireframe.from_geojson(doc).almost_equal(room(), tol=0.05 + 1e-9)


def test_fused_map_from_geojson_sources(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    wf = room().replace(sources=np.array([1, 2, 1, 2, 1, 2, 1, 2, 5, 5], dtype=np.uint64))
    src = _geojson(tmp_path, wf)
    out = tmp_path / "fused.wfm"
    assert main(["encode", str(src), "--stamp-ns", "0", "-o", str(out)]) == 0
    msg = wire_codec.decode(out.read_bytes())
    assert msg.kind == wire_codec.MessageKind.FUSED_MAP and msg.robots == ("r0", "r1", "r2")
    assert main(["encode", str(src), "--kind", "robot", "-o", str(out)]) == 1
    assert "EncodeError" in capsys.readouterr().err


def test_bad_payload_exits_1_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = tmp_path / "good.wfm"
    assert main(["encode", str(_geojson(tmp_path, room())), "-o", str(good)]) == 0
    capsys.readouterr()
    data = good.read_bytes()
    cases = {
        "truncated.wfm": (data[:30], "TruncatedError"),
        "crc.wfm": (data[:-1] + bytes([data[-1] ^ 1]), "ChecksumError"),
        "trailing.wfm": (data + b"\x00", "ExtraDataError"),
        "version.wfm": (data[:1] + b"\x07" + data[2:], "VersionError"),
    }
    for name, (payload, error) in cases.items():
        path = tmp_path / name
        path.write_bytes(payload)
        assert main(["decode", str(path)]) == 1
        captured = capsys.readouterr()
        assert captured.out == ""
        assert captured.err.startswith(error + ": ") and captured.err.count("\n") == 1, captured.err


def test_usage_errors_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["decode", str(tmp_path / "missing.wfm")]) == 2
    bad = tmp_path / "bad.geojson"
    bad.write_text("{not json")
    assert main(["encode", str(bad), "-o", str(tmp_path / "x")]) == 2
    with pytest.raises(SystemExit) as exc:
        main(["frobnicate"])
    assert exc.value.code == 2
    assert "no such file" in capsys.readouterr().err


@pytest.mark.fleet
def test_module_entry_point_pipes(tmp_path: Path) -> None:
    src = _geojson(tmp_path, room())
    enc = subprocess.run(
        [sys.executable, "-m", "wire_codec", "encode", str(src), "--stamp-ns", "1"],
        cwd=ROOT, capture_output=True, check=True, timeout=60,
    )
    assert wire_codec.decode(enc.stdout).wireframe.n_edges == 10
    dec = subprocess.run(
        [sys.executable, "-m", "wire_codec", "decode", "-"],
        cwd=ROOT, input=enc.stdout, capture_output=True, check=True, timeout=60,
    )
    assert dec.stdout.decode().startswith("kind=robot_map sender=cli version=1 ")


# ---------------------------------------------------------------------------------------- bench
def test_occupancy_grid_of_a_square_room() -> None:
    # A 2 x 2 m room at 0.5 m: 4 x 4 cells inside, one padding cell on every side -> 6 x 6.
    wf = Wireframe.from_polylines([[(0, 0), (2, 0), (2, 2), (0, 2)]])
    grid = bench.occupancy_grid(wf, 0.5)
    assert grid.shape == (6, 6)
    assert np.all(grid[2:4, 2:4] == bench.FREE)  # the middle is free
    assert grid[0, 0] == bench.UNKNOWN  # outside
    # A wall on a cell boundary marks the cell above / right of it: y = 0 -> row 1, y = 2 -> row 5.
    assert grid[1, 3] == bench.WALL and grid[5, 3] == bench.WALL
    # The same ring clockwise is an obstacle: nothing inside is free.
    cw = Wireframe.from_polylines([[(0, 0), (0, 2), (2, 2), (2, 0)]])
    assert not np.any(bench.occupancy_grid(cw, 0.5) == bench.FREE)
    assert bench.ros_grid_bytes(grid) == 99 + 36


def test_png_is_a_valid_png() -> None:
    grid = bench.occupancy_grid(room(), 0.2)
    png = bench.png_bytes(grid)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert (height, width) == grid.shape
    idat_len = int.from_bytes(png[33:37], "big")
    assert png[37:41] == b"IDAT"
    raw = zlib.decompress(png[41 : 41 + idat_len])
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(height, width + 1)
    assert np.all(rows[:, 0] == 0)
    assert set(np.unique(rows[:, 1:]).tolist()) <= {0, 205, 254}
    assert png.endswith(b"IEND\xaeB`\x82")


def test_measure_on_a_hand_made_map() -> None:
    r = bench.measure(room(), 0.2, repeat=3)
    assert set(r) == {
        "message_bytes", "body_bytes", "envelope_bytes", "paper_accounting_bytes", "msgpack_float_bytes",
        "png_grid_bytes", "ros_grid_bytes", "encode_us", "decode_us", "vertices", "edges",
    }
    assert r["message_bytes"] == r["body_bytes"] + r["envelope_bytes"]
    assert r["paper_accounting_bytes"] == 200 and (r["vertices"], r["edges"]) == (10, 10)
    assert r["message_bytes"] < r["msgpack_float_bytes"] and r["encode_us"] > 0


def test_bench_run_prints_table_then_json(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bench, "_world_truth", lambda name: room())
    extra = _geojson(tmp_path, room().transformed(wire_codec.codec.Pose(5, 5, 0)))
    args = argparse.Namespace(json=True, paper_small_map=None, museum_map=None, map=str(extra),
                              resolution=0.4, repeat=2, run_filter=[], filter_seed=1, filter_duration=None)
    assert bench.run(args) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].split()[:3] == ["map", "V", "E"]
    result = json.loads(lines[-1])
    assert list(result) == ["paper_small", "museum", "map"]
    assert any(line.startswith("target paper_small body_bytes <= 96: ") for line in lines)


def test_bench_on_a_short_filter_run(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(bench, "_world_truth", lambda name: room())
    args = argparse.Namespace(json=True, paper_small_map=None, museum_map=None, map=None,
                              resolution=0.2, repeat=2,
                              run_filter=["paper-small"], filter_seed=1, filter_duration=4.0)
    assert bench.run(args) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["paper_small"]["vertices"] > 0 and result["museum"]["vertices"] == 10
