"""Golden vectors: a few small maps with their exact bytes checked in, per format version
(tests/golden/codec_v1.json: maps of at most 64 robots, still written as version 1;
tests/golden/codec_v2.json: a fused map of 70 robots, version 2).

Any change to the bytes the encoder writes fails here. If the change is deliberate, bump
``wire_codec.VERSION``, describe the new format in FORMAT.md, add its vectors and write them
with ``python -m tests.test_codec_golden --write`` (it writes codec_v<version>.json for every
version; the old files must not change).
"""

from __future__ import annotations

import json
import math
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

import wire_codec
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from tests.test_codec_util import FUSED, fields_of, message, room

GOLDEN_DIR = Path(__file__).with_name("golden")
GOLDEN = GOLDEN_DIR / "codec_v1.json"


def golden_messages_v2() -> dict[str, tuple[str, wire_codec.MapMessage]]:
    """Version 2: more than 64 robots (masks past bit 63)."""
    robots = tuple(f"r{k:02d}" for k in range(70))
    masks = [1, 1 << 69, (1 << 69) | 1, 1 << 64, 1 << 63, (1 << 70) - 1, 6, 1 << 69, 1, 1 << 40]
    fused = room().replace(sources=np.array(masks, dtype=object))
    return {
        "fused_seventy_robots": (
            "fused map of the L-shaped room from 70 robots r00..r69, masks using bits 0, 1, 2, 40, "
            "63, 64, 69 and all 70; 0.4 m",
            message(fused, kind=FUSED, robots=robots, sender="fusion", frame="fleet",
                    resolution=0.4, pose=Pose(), seq=5, stamp_ns=2),
        ),
    }


def golden_messages() -> dict[str, tuple[str, wire_codec.MapMessage]]:
    square = Wireframe.from_polylines([[(0, 0), (4, 0), (4, 3), (0, 3)]])
    mixed = room()
    labels = np.array([0, 0, 0, 1, 2, 0, 0, 0, 0, 0], dtype=np.uint8)
    lik = np.array([1.0, 1.0, 0.8, 1.0, 0.4, 1.0, 1.0, 0.0, 1.0, 1.0])
    mixed = Wireframe.build(
        mixed.points,
        np.vstack([mixed.edges, [[1, 0], [2, 7]]]),
        labels,
        np.concatenate([lik, [0.5, 1.0]]),
    )
    fused = room().replace(sources=np.array([1, 3, 1, 2, 2, 4, 4, 4, 1, 7], dtype=np.uint64))
    return {
        "empty_robot_map": (
            "no vertices; sender r1, seq 0, stamp 0, identity poses, 0.2 m",
            message(Wireframe.empty(), seq=0, stamp_ns=0, pose=Pose(), origin=Pose()),
        ),
        "square_room": (
            "a 4 x 3 m room, counterclockwise, all nominal, likelihood 1; 0.2 m",
            message(square, seq=42, stamp_ns=123_456_789, pose=Pose(1.5, -2.25, 0.5),
                    origin=Pose(2.0, 3.0, math.pi / 2)),
        ),
        "room_mixed": (
            "L-shaped room with an obstacle, an occlusion and a frontier corner, varied likelihoods, "
            "a reverse (thin wall) edge and an explicit edge, meta; 0.1 m",
            message(mixed, resolution=0.1, seq=99, stamp_ns=5_000_000_000, meta={"stale": ["r2"]}),
        ),
        "fused_three_robots": (
            "fused map of the L-shaped room from robots r1, r2, r3 with per-wall contributor masks; 0.4 m",
            message(fused, kind=FUSED, robots=("r1", "r2", "r3"), sender="fusion", frame="fleet",
                    resolution=0.4, pose=Pose(), seq=3, stamp_ns=1),
        ),
    }


VERSIONED = {1: golden_messages, 2: golden_messages_v2}


def _load(version: int = 1) -> dict[str, str]:
    doc = json.loads((GOLDEN_DIR / f"codec_v{version}.json").read_text())
    return {v["name"]: v["hex"] for v in doc["vectors"]}


CASES = [(v, name) for v, make in VERSIONED.items() for name in make()]


@pytest.mark.parametrize(("version", "name"), CASES)
def test_encoder_writes_the_golden_bytes(version: int, name: str) -> None:
    data = wire_codec.encode(VERSIONED[version]()[name][1])
    assert data.hex() == _load(version)[name]
    assert data[1] == version


@pytest.mark.parametrize(("version", "name"), CASES)
def test_golden_bytes_decode_to_the_map(version: int, name: str) -> None:
    msg = VERSIONED[version]()[name][1]
    out = wire_codec.decode(bytes.fromhex(_load(version)[name]))
    assert (out.kind, out.sender, out.seq, out.stamp_ns, out.frame, out.robots, out.meta) == (
        msg.kind, msg.sender, msg.seq, msg.stamp_ns, msg.frame, msg.robots, msg.meta
    )
    assert out.wireframe.almost_equal(msg.wireframe, tol=msg.resolution / 2 + 1e-9, likelihood_tol=1 / 30)


def test_square_room_bytes_by_hand() -> None:
    # The body of the square room, bit by bit (FORMAT.md, "Worked example").
    data = bytes.fromhex(_load()["square_room"])
    body = wire_codec.decode(data).wireframe
    assert body.points.tolist() == [[0, 0], [4, 0], [4, 3], [0, 3]]
    assert body.edges.tolist() == [[0, 1], [1, 2], [2, 3], [3, 0]]
    assert fields_of(data)[11].hex() == "29801b12bdb587a780"


def test_golden_file_lists_every_vector() -> None:
    assert sorted(VERSIONED) == list(wire_codec.VERSIONS)
    for version, make in VERSIONED.items():
        doc = json.loads((GOLDEN_DIR / f"codec_v{version}.json").read_text())
        assert doc["version"] == version
        assert sorted(v["name"] for v in doc["vectors"]) == sorted(make())


def write() -> None:
    for version, make in VERSIONED.items():
        vectors = [
            {"name": name, "description": text, "hex": wire_codec.encode(msg).hex()}
            for name, (text, msg) in make().items()
        ]
        doc = {"version": version, "format": "wire_codec/FORMAT.md", "vectors": vectors}
        path = GOLDEN_DIR / f"codec_v{version}.json"
        path.parent.mkdir(exist_ok=True)
        path.write_text(json.dumps(doc, indent=2) + "\n")
        print(f"wrote {path}")


def test_format_md_worked_example_matches_the_golden_vector() -> None:
    text = (Path(wire_codec.__file__).with_name("FORMAT.md")).read_text(encoding="utf-8")
    block = text.split("## 5. Worked example", 1)[1].split("```", 2)[1]
    hex_bytes = "".join(line.split("  ")[0].replace(" ", "") for line in block.strip().splitlines())
    assert hex_bytes == _load()["square_room"]
    assert zlib.crc32(b"123456789") == 0xCBF43926  # the check value FORMAT.md quotes


if __name__ == "__main__" and "--write" in sys.argv:
    write()
