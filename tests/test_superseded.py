"""Superseded maps (issue 21): of one robot key's payloads drained together only the newest is
decoded (:meth:`FusionState.offer_latest`); the older ones are read up to their header
(``superseded``, or counted as malformed or rejected when the header says so), and their publish
stamps still start the latency clock. Also the fusion service's side (:func:`by_key`,
``FusionService._take``) without a network."""

from __future__ import annotations

from unittest.mock import patch

import numpy as np
import pytest

import agents.fleet.fusion.state as state_mod
from agents.fleet.bus import FleetKeys
from agents.fleet.fusion import FusionConfig, FusionState, InputLimits, encode_message
from agents.fleet.fusion.intake import by_key
from agents.fleet.fusion.quarantine import QuarantineConfig
from agents.fleet.fusion.state import MAX_TRANSPORT_NS
from agents.sim.world import load_world
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from tests.test_quarantine import part
from wire_codec.message import MapMessage, MessageKind

S = 10**9
BOOT = 10**18
NOW = BOOT + 100 * S
ORIGIN = Pose(50.0, 50.0, 0.0)
TRUTH = load_world("museum").truth


def raw(rid: str, seq: int, radius: float = 10.0, stamp_ns: int | None = None, sender: str | None = None,
        kind: MessageKind = MessageKind.ROBOT_MAP, wf: Wireframe | None = None) -> bytes:
    """Robot ``rid``'s map number ``seq``: the museum's walls within ``radius`` of its start,
    published at ``stamp_ns`` (default ``NOW - (10 - seq) * 0.1 s``)."""
    wf = part(TRUTH, (ORIGIN.x, ORIGIN.y), radius) if wf is None else wf
    return encode_message(MapMessage(
        kind=kind, sender=sender or rid, seq=seq,
        stamp_ns=NOW - (10 - seq) * S // 10 if stamp_ns is None else stamp_ns,
        pose=Pose.identity(), frame=f"odom/{rid}", origin=ORIGIN, resolution=0.05,
        wireframe=wf.transformed(ORIGIN.inverse()), meta={"boot": BOOT, "t": float(seq), "step": seq},
    ))  # fmt: skip


def stamp(seq: int) -> int:
    return NOW - (10 - seq) * S // 10


def state() -> FusionState:
    return FusionState(FusionConfig(threshold=0.4, refine=False), limits=InputLimits(),
                       quarantine=QuarantineConfig())


class Decodes:
    """Counts the full decodes FusionState makes."""

    def __init__(self) -> None:
        self.n = 0
        self._real = state_mod.decode_message

    def __call__(self, data: bytes, limits=None, *rest):  # type: ignore[no-untyped-def]
        self.n += 1
        return self._real(data, limits, *rest)


def offer_latest(st: FusionState, payloads: list[bytes], rid: str = "r1", now: int = NOW):
    counter = Decodes()
    with patch.object(state_mod, "decode_message", counter):
        taken = st.offer_latest(payloads, rid, now)
    return taken, counter.n


def test_three_maps_of_one_robot_decode_one_and_time_from_the_oldest() -> None:
    st = state()
    taken, decodes = offer_latest(st, [raw("r1", 1, 8.0), raw("r1", 2, 9.0), raw("r1", 3, 10.0)])
    assert decodes == 1 and taken.changed and taken.index == 2 and taken.drops == ()
    s = st.stats
    assert (s.received, s.accepted, s.superseded, s.dropped) == (3, 1, 2, 0)
    assert st.robots["r1"].key[1] == 3  # the newest is the robot's map
    assert st.stats.as_dict()["superseded"] == 2
    assert st.pending_stamps() == [stamp(1)]  # the latency clock started at the oldest publish
    st.fuse()
    published = NOW + 5 * S // 1000
    assert st.take_latencies(published) == [pytest.approx((published - stamp(1)) / 1e6)]


def test_one_payload_is_plain_offer_and_the_map_is_what_offering_all_gives() -> None:
    maps = [raw("r1", k, 6.0 + k) for k in range(1, 5)]
    one, every = state(), state()
    taken, decodes = offer_latest(one, maps[:1])
    assert decodes == 1 and taken.changed and one.stats.superseded == 0
    offer_latest(one, maps[1:])
    for data in maps:
        every.offer(data, "r1", NOW)
    assert one.robots["r1"].raw == every.robots["r1"].raw and one.robots["r1"].key == every.robots["r1"].key
    one.fuse()
    every.fuse()
    assert one.fused.content_digest() == every.fused.content_digest()


def test_a_superseded_stamp_counts_at_most_max_transport_old_and_never_newer() -> None:
    st = state()
    ancient = raw("r1", 1, stamp_ns=NOW - 10 * MAX_TRANSPORT_NS)
    offer_latest(st, [ancient, raw("r1", 2)])
    assert st.pending_stamps() == [NOW - MAX_TRANSPORT_NS]
    st = state()
    future = raw("r1", 1, stamp_ns=NOW + S)  # a forged stamp after the newest's: the newest's counts
    offer_latest(st, [future, raw("r1", 2)])
    assert st.pending_stamps() == [stamp(2)]


def test_an_unchanged_newest_map_gives_no_latency_sample() -> None:
    st = state()
    st.offer(raw("r1", 1), "r1", NOW)
    st.fuse()
    st.take_latencies(NOW)
    taken, _ = offer_latest(st, [raw("r1", 2, 9.0), raw("r1", 3)])  # the same content as seq 1
    assert not taken.changed and st.stats.superseded == 1 and st.pending_stamps() == []


def test_a_malformed_older_payload_is_counted_and_its_stamp_ignored() -> None:
    st = state()
    broken = bytearray(raw("r1", 1))
    broken[-1] ^= 1  # CRC
    taken, decodes = offer_latest(st, [bytes(broken), b"\x00garbage", raw("r1", 2), raw("r1", 3)])
    assert decodes == 1 and taken.changed
    s = st.stats
    assert (s.received, s.accepted, s.superseded, s.malformed) == (4, 1, 1, 2)
    assert s.malformed_by == {"ChecksumError": 1, "TruncatedError": 1}
    assert [d[0] for d in taken.drops] == ["malformed", "malformed"]
    assert st.pending_stamps() == [stamp(2)]


def test_spoofed_older_payloads_are_rejected_by_their_header() -> None:
    st = state()
    lie = raw("r2", 1, sender="r2")  # on r1's key
    fused = raw("r1", 2, kind=MessageKind.FUSED_MAP)
    taken, decodes = offer_latest(st, [lie, fused, raw("r1", 3)])
    assert decodes == 1 and taken.changed
    assert st.stats.rejected_by == {"sender_mismatch": 1, "not_robot_map": 1}
    assert st.stats.superseded == 0 and st.pending_stamps() == [stamp(3)]


def test_a_malformed_newest_is_dropped_and_the_one_before_taken() -> None:
    st = state()
    taken, decodes = offer_latest(st, [raw("r1", 1), raw("r1", 2), raw("r1", 3)[:-3]])
    assert decodes == 2 and taken.changed and taken.index == 1
    s = st.stats
    assert (s.received, s.accepted, s.superseded, s.malformed) == (3, 1, 1, 1)
    assert s.malformed_by == {"TruncatedError": 1}
    assert st.robots["r1"].key[1] == 2 and st.pending_stamps() == [stamp(1)]
    # every payload bad: each one counted, nothing taken
    st = state()
    taken, decodes = offer_latest(st, [b"\x01", b"\x02", b"\x03"])
    assert not taken.changed and decodes == 3 and taken.index == 0
    assert st.stats.malformed == 3 and st.stats.received == 3 and "r1" not in st.robots


def test_an_absurd_newest_falls_back_but_is_never_taken() -> None:
    st = state()
    dense = Wireframe.build(np.array([[50.0 + 0.01 * k, 50.0] for k in range(40)]),
                            [(k, k + 1) for k in range(39)])  # 40 vertices in one square metre
    taken, decodes = offer_latest(st, [raw("r1", 1), raw("r1", 2, wf=dense)])
    assert decodes == 2 and taken.changed and st.robots["r1"].key[1] == 1
    assert st.stats.absurd_by == {"budget_density": 1} and st.stats.superseded == 0


def test_a_quarantined_newest_ends_the_walk() -> None:
    """The older maps of the batch are not tried: the robot keeps its last accepted map, and the
    newest is compared with that map, never with a skipped one."""
    st = state()
    assert st.offer(raw("r1", 1, 30.0), "r1", NOW - S)
    st.fuse()
    shifted = part(TRUTH, (50.0, 50.0), 30.0).transformed(Pose(8.0, 5.0, 0.2))
    taken, decodes = offer_latest(st, [raw("r1", 2, 30.0), raw("r1", 3, wf=shifted)])
    assert decodes == 1 and not taken.changed
    assert st.stats.quarantined_by == {"history_walls": 1} and st.stats.superseded == 1
    assert st.robots["r1"].key[1] == 1 and [d[0] for d in taken.drops] == ["quarantined"]


def test_by_key_groups_in_arrival_order() -> None:
    items = [("a", b"1", 1), ("b", b"2", 2), ("a", b"3", 3), ("c", b"4", 4), ("b", b"5", 5)]
    assert by_key(items) == [("a", [(b"1", 1), (b"3", 3)]), ("c", [(b"4", 4)]), ("b", [(b"2", 2), (b"5", 5)])]
    assert by_key([]) == []


def test_the_service_takes_each_robots_newest_map() -> None:
    """FusionService._take without a network: one decode per robot, the counters, the transport
    sample of the map taken, the drop log."""
    from agents.fleet.fusion.service import FusionService, ServeOptions

    keys = FleetKeys("t")
    svc = FusionService(None, keys, ServeOptions(quarantine=None, budget=None))
    notes: list[tuple[str, str]] = []
    svc.drops.note = lambda reason, key, detail="": notes.append((reason, key))  # type: ignore[method-assign]
    items = [
        (keys.robot_map("r1"), raw("r1", 1), NOW),
        (keys.robot_map("r2"), raw("r2", 1), NOW),
        (keys.robot_map("r1"), raw("r1", 2, 12.0), NOW + 1),
        (keys.robot_map("r1"), b"junk", NOW + 2),
        ("t/elsewhere", b"x", NOW + 3),
    ]
    counter = Decodes()
    with patch.object(state_mod, "decode_message", counter):
        svc._take(items)
    st = svc.state.stats
    assert counter.n == 3  # r1's junk, then its seq 2; r2's only map
    assert (st.received, st.accepted, st.superseded, st.malformed, st.rejected) == (5, 2, 1, 1, 1)
    assert svc.dirty == {"r1", "r2"} and svc.state.robots["r1"].key[1] == 2
    assert sorted(notes) == [("malformed", keys.robot_map("r1")), ("rejected", "t/elsewhere")]
    assert svc.stats_doc()["stats"]["superseded"] == 1
    assert len(svc.transport_ms) == 2
