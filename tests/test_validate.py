"""Hostile values in every field of every bus message: each decoder either returns checked
values or raises ``validate.Invalid`` (a ``ValueError`` with a reason), and every consumer
(the fusion core, the recorder, ``run``'s progress line, ``watch``) takes what the decoders
return without raising. One place checks (:mod:`agents.fleet.validate`); these tests hold it
to that."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agents.commands.run import Progress
from agents.commands.watch import Watcher
from agents.fleet import validate
from agents.fleet.bus import FleetKeys, decode_pose, decode_viz, encode_pose, encode_viz, pack_wireframe
from agents.fleet.fusion import FusionState, encode_message
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from wire_codec.message import MapMessage, MessageKind

ROOM = Wireframe.build(
    np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0]]), np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
)

# values an attacker puts in a field: every msgpack type, extremes of each
HOSTILE = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(1 << 63), max_value=(1 << 64) - 1),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e300, -1e300, 5e-324, -0.0, 1e19, 2.0**63]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.sampled_from(["x", "0", "nan", "1e300", "r1/../r2", "*" * 300, "\x00"]),
    st.binary(max_size=16),
    st.lists(st.integers(-5, 5), max_size=4),
    st.lists(st.floats(allow_nan=True), min_size=3, max_size=3),
    st.dictionaries(st.text(max_size=4), st.integers(-(1 << 63), (1 << 64) - 1), max_size=3),
)
GOOD_POSE = msgpack.unpackb(
    encode_pose(seq=1, t=1.0, stamp_ns=1, odom=Pose(1, 2, 0.1), fleet=Pose(1, 2, 0.1), truth=Pose(1, 2, 0.1),
                status={"step": 3, "t": 1.0, "vertices": 4, "edges": 4, "maps_sent": 1, "bytes_sent": 9,
                        "finished": False}),
    raw=False,
)
GOOD_VIZ = msgpack.unpackb(
    encode_viz(t=1.0, scan=ROOM, pose=Pose(0, 0, 0), particles=[ROOM, ROOM], weights=[0.5, 0.5]), raw=False
)


def _recorder() -> Any:
    from agents.files.rerun_log import FleetRecorder

    d = tempfile.mkdtemp(prefix="wiremap-validate-")
    return FleetRecorder(Path(d) / "r.rrd")


_REC: list[Any] = []


def recorder() -> Any:
    if not _REC:
        _REC.append(_recorder())
    return _REC[0]


def progress_line(status: dict[str, Any]) -> str:
    p = Progress(["r1"], enabled=False)
    p.status["r1"] = status
    return p.line("r1")


@settings(max_examples=400)
@given(
    field=st.sampled_from(["seq", "t", "stamp_ns", "odom", "fleet", "truth", "status"]),
    value=HOSTILE,
    sub=st.sampled_from(["step", "t", "vertices", "edges", "maps_sent", "bytes_sent", "finished",
                         "step_ms", "zz"]),
)
def test_pose_hostile_field(field: str, value: Any, sub: str) -> None:
    d = dict(GOOD_POSE)
    if field == "status" and not isinstance(value, dict):
        d["status"] = {**GOOD_POSE["status"], sub: value}
    else:
        d[field] = value
    data = msgpack.packb(d, use_bin_type=True)
    try:
        p = decode_pose(data)
    except validate.Invalid as exc:
        assert exc.reason
        return
    # every consumer of a pose: the progress line, the recorder
    assert 0.0 <= p["t"] <= validate.MAX_SIM_T
    progress_line(p["status"])
    recorder().log_robot_pose("r1", p["t"], p["fleet"], p["truth"])


@settings(max_examples=200)
@given(
    field=st.sampled_from(["t", "pose", "scan", "particles", "weights"]),
    value=HOSTILE,
)
def test_viz_hostile_field(field: str, value: Any) -> None:
    d = dict(GOOD_VIZ)
    d[field] = value
    try:
        v = decode_viz(msgpack.packb(d, use_bin_type=True))
    except validate.Invalid:
        return
    recorder().log_robot_viz("r1", v["t"], Pose(0, 0, 0), v["pose"], v["scan"], v["particles"], v["weights"])


@settings(max_examples=100)
@given(data=st.binary(max_size=300))
def test_side_payload_bytes(data: bytes) -> None:
    for decode in (decode_pose, decode_viz, validate.fused_map, validate.stats_doc):
        try:
            decode(data)
        except validate.Invalid:
            pass


def test_viz_wireframe_bytes_hostile() -> None:
    bad_scan = pack_wireframe(ROOM)
    bad_scan["p"] = np.array([[np.nan, 0.0]] * 4, dtype="<f4").tobytes()
    for scan in (bad_scan, {**pack_wireframe(ROOM), "e": b"\xff" * 8}, {"p": b"", "l": b"x", "e": b""}):
        with pytest.raises(validate.Invalid):
            decode_viz(msgpack.packb({**GOOD_VIZ, "scan": scan}, use_bin_type=True))


START = Pose(1.0, 1.0, 0.0)


def robot_map(meta: Any, seq: int = 1, stamp_ns: int = 5, origin: Pose = START) -> MapMessage:
    return MapMessage(
        kind=MessageKind.ROBOT_MAP, sender="r1", seq=seq, stamp_ns=stamp_ns, pose=Pose.identity(),
        frame="odom/r1", origin=origin, resolution=0.05, wireframe=ROOM, meta=meta,
    )


META_VALUES = st.one_of(
    HOSTILE.filter(lambda v: not isinstance(v, list) or all(isinstance(x, (int, float)) for x in v)),
)


@settings(max_examples=300)
@given(key=st.sampled_from(["boot", "t", "step", "zz"]), value=META_VALUES)
def test_robot_map_meta_hostile(key: str, value: Any) -> None:
    meta = {"boot": 10, "t": 1.0, "step": 1, key: value}
    try:
        data = encode_message(robot_map(meta))
    except (ValueError, TypeError, OverflowError):
        return  # the encoder refuses it: it never travels
    st_ = FusionState()
    st_.offer(data, "r1", now_ns=10**19 // 2)
    st_.fuse()
    # the fusion's own consumers of what it accepted
    t = st_.sim_time()
    assert 0.0 <= t <= validate.MAX_SIM_T
    recorder().log_fused(t, st_.fused, st_.fused_robots, st_.version, None)
    st_.stats.as_dict()


@settings(max_examples=200)
@given(
    seq=st.integers(min_value=0, max_value=(1 << 64) - 1),
    stamp=st.integers(min_value=0, max_value=(1 << 64) - 1),
    boot=st.integers(min_value=0, max_value=(1 << 64) - 1),
)
def test_robot_map_numbers_hostile(seq: int, stamp: int, boot: int) -> None:
    try:
        data = encode_message(robot_map({"boot": boot, "t": 1.0}, seq=seq, stamp_ns=stamp))
    except (ValueError, OverflowError):
        return
    st_ = FusionState()
    st_.offer(data, "r1", now_ns=1_000_000)
    st_.fuse()
    st_.stats.as_dict()


@settings(max_examples=200)
@given(key=st.sampled_from(["version", "threshold", "stale", "t", "zz"]), value=META_VALUES)
def test_fused_map_meta_hostile(key: str, value: Any) -> None:
    msg = MapMessage(
        kind=MessageKind.FUSED_MAP, sender="fusion", seq=3, stamp_ns=5, pose=Pose.identity(), frame="fleet",
        origin=Pose.identity(), resolution=0.05, wireframe=ROOM, robots=("r1",),
        meta={"version": 3, "threshold": 0.2, "stale": [], key: value},
    )
    try:
        data = encode_message(msg)
    except (ValueError, TypeError, OverflowError):
        return
    w = Watcher(FleetKeys(), None)
    line = w.handle(data)
    assert line is not None or w.malformed == 1


def test_admin_request() -> None:
    assert validate.admin_request("forget=r7") == ("forget", "r7")
    for bad in ("", "forget=../x", "forget=" + "a" * 300, "drop=r1", None, 12):
        with pytest.raises(validate.Invalid):
            validate.admin_request(bad)


def test_stats_doc_get_int() -> None:
    doc = validate.stats_doc(b'{"version": 1e300, "n": "x", "ok": 3}')
    assert validate.get_int(doc, "version") == 0 and validate.get_int(doc, "n") == 0
    assert validate.get_int(doc, "ok") == 3
