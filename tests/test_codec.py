"""Wire codec: round trips, sizes, the envelope's fields, encoder refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

import wire_codec
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe
from tests.test_codec_util import FUSED, ROBOT, check_round_trip, fields_of, message, messages, room
from wire_codec.bits import BitReader, BitWriter, best_eg_order, best_eg_orders, eg_cost
from wire_codec.body import chain_order, encode_body
from wire_codec.codec import encode_with_plan


# ---------------------------------------------------------------------------------------- bits
def test_exp_golomb_codes_match_the_textbook() -> None:
    # Order 0: 0 -> 1, 1 -> 010, 2 -> 011, 3 -> 00100; order 2: 0 -> 100, 5 -> 01001.
    for value, k, code in [(0, 0, "1"), (1, 0, "010"), (2, 0, "011"), (3, 0, "00100"), (0, 2, "100"),
                           (5, 2, "01001")]:
        w = BitWriter()
        w.eg(value, k)
        assert "".join(map(str, w.to_bits().tolist())) == code
        block = BitWriter()
        block.eg_block(np.array([value]), k)
        assert np.array_equal(block.to_bits(), w.to_bits())
        assert eg_cost(np.array([value]), k) == len(code)


def test_eg_block_puts_prefixes_first_and_reads_back() -> None:
    w = BitWriter()
    w.eg_block(np.array([1, 0, 3]), 0)  # prefixes 01 1 001, then mantissas 0, (none), 00
    assert "".join(map(str, w.to_bits().tolist())) == "011001" + "000"
    rng = np.random.default_rng(3)
    values = rng.integers(0, 2**40, size=500)
    orders = rng.integers(0, 16, size=500)
    w = BitWriter()
    w.eg_block(values, orders)
    w.fixed(np.array([5, 2**64 - 1], dtype=np.uint64), 64)
    r = BitReader(w.to_bytes())
    assert np.array_equal(r.eg_block(500, orders, "x"), values)
    assert r.fixed(2, 64, "y").tolist() == [5, 2**64 - 1]


def test_best_eg_order_picks_the_cheapest() -> None:
    values = np.array([100, 120, 90, 110, 101])
    k = best_eg_order(values)
    assert all(eg_cost(values, k) <= eg_cost(values, j) for j in range(16))
    assert k == 7 and eg_cost(values, 7) == 5 * 8  # u = v + 128 has 8 bits: 0 zeros, 1, 7 mantissa bits


# ---------------------------------------------------------------------------------------- body
def test_l_shaped_room_costs_what_the_format_says() -> None:
    wf = room()
    body = encode_body(wf, 0.2, None)
    # Every corner of both rings is one move along one axis except the first of each ring.
    assert len(body.data) <= 24
    assert sorted(body.vertex_order.tolist()) == list(range(10))
    data = check_round_trip(message(wf))
    assert len(data) - len(body.data) <= 70


def test_rectilinear_ring_costs_about_one_bit_per_shared_coordinate() -> None:
    # A 40-corner staircase ring: every corner shares x or y with the previous one.
    steps = [(i // 2 + (i % 2), i // 2) for i in range(40)]
    ring = [(x * 1.0, y * 1.0) for x, y in steps] + [(0.0, 20.0)]
    wf = Wireframe.from_polylines([ring])
    body = encode_body(wf, 0.2, None)
    # 41 vertices: <= 1 class bit + 1 sign bit + ~4 magnitude bits each, 1 chain bit per edge.
    assert body.n_bits <= 41 * 7 + 41 + 40
    check_round_trip(message(wf))


def test_chain_order_follows_edges_and_covers_every_vertex() -> None:
    edges = np.array([[3, 1], [1, 4], [4, 3], [0, 2]], dtype=np.int32)
    order = chain_order(6, edges).tolist()
    # Paths from their heads in index order (0 -> 2, the lone vertex 5), then the cycle
    # 3 -> 1 -> 4 -> 3 from its lowest vertex.
    assert order == [0, 2, 5, 1, 4, 3]


def test_empty_and_single_vertex_maps() -> None:
    assert encode_body(Wireframe.empty(), 0.2, None).data == b"\x80"
    check_round_trip(message(Wireframe.empty()))
    check_round_trip(message(Wireframe.empty(), kind=FUSED, robots=("a", "b")))
    one = Wireframe.build([[1.234, -5.678]], labels=[Label.FRONTIER])
    out = wire_codec.decode(check_round_trip(message(one))).wireframe
    assert out.points.tolist() == [[1.2, -5.6]] and out.labels.tolist() == [2]


def test_thin_wall_repeat_and_reverse_edges_survive() -> None:
    wf = Wireframe.build(
        [[0, 0], [4, 0], [4, 3], [0, 3]],
        [[0, 1], [1, 2], [2, 3], [3, 0], [1, 0], [0, 1], [2, 0], [0, 2]],
        likelihood=[1, 1, 1, 1, 0.5, 0.25, 0, 1],
    )
    check_round_trip(message(wf))


def test_likelihood_quantisation_is_exact_at_the_ends() -> None:
    lik = np.linspace(0.0, 1.0, 31)
    wf = Wireframe.build(np.arange(64, dtype=float).reshape(32, 2), [[k, k + 1] for k in range(31)],
                         likelihood=lik)
    got = wire_codec.decode(check_round_trip(message(wf))).wireframe.likelihood
    assert got.min() == 0.0 and got.max() == 1.0
    assert np.max(np.abs(np.sort(got) - lik)) <= 1 / 30 + 1e-12


def test_fused_map_sources_and_robots_round_trip() -> None:
    wf = room()
    src = np.array([1, 3, 1, 2, 2, 4, 4, 4, 1, 7], dtype=np.uint64)
    fused = message(wf.replace(sources=src), kind=FUSED, robots=("r1", "r2", "r3"), sender="fusion",
                    frame="fleet")
    out = wire_codec.decode(check_round_trip(fused))
    assert out.robots == ("r1", "r2", "r3") and sorted(out.wireframe.sources.tolist()) == sorted(src.tolist())
    full = message(wf.replace(sources=np.full(10, 2**64 - 1, dtype=np.uint64)), kind=FUSED,
                   robots=tuple(f"r{k}" for k in range(64)))
    assert wire_codec.decode(check_round_trip(full)).wireframe.sources.tolist() == [2**64 - 1] * 10


def test_far_away_coordinates_keep_half_step_accuracy() -> None:
    wf = room().transformed(Pose(-3.0e6, 9.5e6, 0.3))
    check_round_trip(message(wf, resolution=0.05))
    check_round_trip(message(wf, resolution=0.001))


@settings(max_examples=150, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(messages())
def test_round_trip_property(msg: wire_codec.MapMessage) -> None:
    check_round_trip(msg)


@settings(max_examples=15, deadline=5000, suppress_health_check=[HealthCheck.too_slow])
@given(messages(robot_counts=(65, 128, 200, 4096)))
def test_round_trip_property_past_64_robots(msg: wire_codec.MapMessage) -> None:
    """Fused maps of more than 64 robots (masks past bit 63, Python ints) travel as format
    version 2 and come back bit for bit, through both decoders."""
    data = check_round_trip(msg)
    assert data[1] == 2
    if msg.wireframe.n_edges:
        assert msg.wireframe.sources.dtype == object
        assert wire_codec.decode(data).wireframe.sources.dtype == object


@given(messages(robot_counts=(1, 3, 8, 64)))
def test_maps_of_at_most_64_robots_are_version_1(msg: wire_codec.MapMessage) -> None:
    """Every message that version 1 can carry is written as version 1 (old decoders read it)."""
    assert wire_codec.encode(msg)[1] == 1


@given(messages(max_vertices=400))
def test_round_trip_property_larger_maps(msg: wire_codec.MapMessage) -> None:
    check_round_trip(msg)


def test_decoding_is_deterministic_and_reencoding_is_stable() -> None:
    msg = message(room(), resolution=0.3)
    data = wire_codec.encode(msg)
    assert wire_codec.encode(msg) == data
    once = wire_codec.decode(data)
    again = wire_codec.decode(wire_codec.encode(once))
    assert again.wireframe.almost_equal(once.wireframe, tol=1e-12)


# ---------------------------------------------------------------------------------------- envelope
def test_envelope_layout() -> None:
    msg = message(room(), pose=Pose(1.2345, -2.0, -0.5), origin=Pose(10.0, 0.0, math.pi / 2),
                  meta={"stale": ["r2"]})
    data = wire_codec.encode(msg)
    assert data[0] == 0x9D and data[1] == 1 and data[-5] == 0xCE  # version 1: it fits (<= 64 robots)
    f = fields_of(data)
    assert f[:5] == [1, 1, "r1", 7, 1_700_000_000_000_000_000]
    assert f[5] == [1234, -2000, -500000] and f[6] == "odom/r1" and f[7] == [10000, 0, 1570796]
    assert f[8] == 200 and f[9] == [] and f[10] == {"stale": ["r2"]}
    assert isinstance(f[11], bytes)


def test_resolution_travels_in_whole_millimetres() -> None:
    msg = message(room(), resolution=0.2004)
    out = wire_codec.decode(wire_codec.encode(msg))
    assert out.resolution == 0.2
    # The grid the encoder used is the one the decoder knows: every vertex on it.
    assert np.allclose(out.wireframe.points / 0.2, np.rint(out.wireframe.points / 0.2), atol=1e-9)


def test_paper_small_sized_map_meets_the_size_targets() -> None:
    # A 42-corner rectilinear map like paper-small (15 x 15 m, several rooms) at 0.2 m.
    rings = [
        [(0, 0), (15, 0), (15, 15), (0, 15)],
        [(2, 2), (2, 5), (5, 5), (5, 2)],
        [(7, 3), (7, 4), (9, 4), (9, 3)],
        [(10, 10), (10, 12.6), (12.4, 12.6), (12.4, 10)],
        [(3, 9), (3, 13), (4, 13), (4, 10), (7, 10), (7, 9)],
        [(1, 7), (1, 7.4), (13, 7.4), (13, 7)],
    ]
    wf = Wireframe.from_polylines(rings * 2)  # twice over (offset below) to reach 42 corners
    pts = wf.points.copy()
    pts[wf.n_vertices // 2 :] += (20.0, 0.0)
    wf = wf.replace(points=pts)
    assert wf.n_vertices >= 40
    data, body = encode_with_plan(message(wf, pose=Pose(12.345, 6.789, 1.2345), seq=1234))
    assert len(body.data) <= 96 and len(data) <= 160


# ---------------------------------------------------------------------------------------- encoder refusals
@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"resolution": 0.0}, "resolution"),
        ({"resolution": -0.2}, "resolution"),
        ({"resolution": float("nan")}, "resolution"),
        ({"resolution": 1e-4}, "resolution"),
        ({"resolution": 1e4}, "resolution"),
        ({"sender": ""}, "sender"),
        ({"seq": -1}, "seq"),
        ({"stamp_ns": 2**64}, "stamp_ns"),
        ({"robots": ("r1",)}, "robots"),
        ({"meta": {1: "x"}}, "meta"),
        ({"meta": {"x": object()}}, "meta"),
    ],
)
def test_encoder_refuses_what_cannot_travel(change: dict[str, object], reason: str) -> None:
    fields = {"resolution": 0.2, "sender": "r1", "seq": 1, "stamp_ns": 0, "robots": (), "meta": {}}
    fields.update(change)
    msg = message(room(), **fields)  # type: ignore[arg-type]
    with pytest.raises(wire_codec.EncodeError, match=reason):
        wire_codec.encode(msg)


def test_encoder_refuses_bad_sources_and_far_points() -> None:
    src = room().replace(sources=np.ones(10, dtype=np.uint64))
    with pytest.raises(wire_codec.EncodeError, match="contributor"):
        wire_codec.encode(message(src))
    with pytest.raises(wire_codec.EncodeError, match="contributor"):
        wire_codec.encode(message(src.replace(sources=np.full(10, 4, dtype=np.uint64)), kind=FUSED,
                                  robots=("a", "b")))
    with pytest.raises(wire_codec.EncodeError, match="at most 4096"):
        wire_codec.encode(message(room(), kind=FUSED, robots=tuple(f"r{k}" for k in range(4097))))
    wide = room().replace(sources=np.array([1 << 70] * 10, dtype=object))
    with pytest.raises(wire_codec.EncodeError, match="contributor"):
        wire_codec.encode(message(wide, kind=FUSED, robots=tuple(f"r{k}" for k in range(70))))
    with pytest.raises(wire_codec.EncodeError, match="contributor"):
        wire_codec.encode(message(wide, kind=FUSED, robots=("a", "b")))
    with pytest.raises(wire_codec.EncodeError, match="distinct"):
        wire_codec.encode(message(room(), kind=FUSED, robots=("a", "a")))
    far = Wireframe.build([[1e17, 0.0]])
    with pytest.raises(wire_codec.EncodeError, match="origin"):
        wire_codec.encode(message(far, resolution=0.2))
    assert isinstance(wire_codec.EncodeError("x"), ValueError)
    assert ROBOT != FUSED


def test_best_eg_orders_per_group_matches_one_by_one() -> None:
    rng = np.random.default_rng(8)
    groups = [rng.integers(0, 2**s, size=c) for s, c in [(3, 10), (12, 0), (20, 7), (1, 1), (9, 0)]]
    orders, costs = best_eg_orders(np.concatenate(groups), [g.size for g in groups])
    for g, k, c in zip(groups, orders, costs):
        assert k == best_eg_order(g) and c == eg_cost(g, k)
        assert all(c <= eg_cost(g, j) for j in range(16))


def test_encode_reuses_the_body_of_the_same_map_and_gives_the_same_bytes() -> None:
    """A map sent again with a new envelope (heartbeat, change probe) reuses its encoded body
    (wire_codec.codec keeps the last few by Wireframe object): the bytes are exactly those of
    a fresh encoding."""
    from dataclasses import replace

    from wire_codec import MapMessage, MessageKind, codec, encode
    from wire_codec.codec import encode_with_plan

    wf = Wireframe.build([(0.0, 0.0), (4.0, 0.0), (4.0, 3.0)], [(0, 1), (1, 2)], [Label.NOMINAL] * 3)
    msg = MapMessage(kind=MessageKind.ROBOT_MAP, sender="r1", seq=1, stamp_ns=5,
                     pose=Pose.identity(), frame="",
                     origin=Pose.identity(), resolution=0.05, wireframe=wf, meta={"boot": 1})
    first = encode(msg)
    assert codec._shared_bodies.holds(wf)
    again = replace(msg, seq=2, stamp_ns=6)
    assert encode(again) == encode_with_plan(again)[0]
    assert encode(msg) == first
    # another resolution is another body
    coarse = replace(msg, resolution=0.2)
    assert encode(coarse) == encode_with_plan(coarse)[0] != first
    for k in range(2 * codec._shared_bodies.max_entries):  # bounded
        encode(replace(msg, wireframe=wf.transformed(Pose(0.1 * k, 0.0, 0.0))))
    assert len(codec._shared_bodies) == codec._shared_bodies.max_entries
    assert not codec._shared_bodies.holds(wf)


def test_a_callers_own_body_cache_keeps_its_maps_and_gives_the_same_bytes() -> None:
    """A replayed recording's maps encoded through its own cache, as large as the recording:
    every map's body stays held however many other maps the shared cache sees meanwhile, and
    every message is byte for byte a fresh encoding."""
    from wire_codec import BodyCache, MapMessage, MessageKind, encode
    from wire_codec.codec import encode_with_plan

    with pytest.raises(ValueError, match="at least one"):
        BodyCache(0)
    base = Wireframe.build([(0.0, 0.0), (4.0, 0.0), (4.0, 3.0)], [(0, 1), (1, 2)], [Label.NOMINAL] * 3)
    frames = [base.transformed(Pose(0.3 * k, 0.1 * k, 0.01 * k)) for k in range(100)]
    mine = BodyCache(len(frames))
    for rnd in range(2):
        for k, wf in enumerate(frames):
            msg = MapMessage(kind=MessageKind.ROBOT_MAP, sender="r1", seq=1 + k + rnd * 100, stamp_ns=5,
                             pose=Pose.identity(), frame="", origin=Pose.identity(), resolution=0.05,
                             wireframe=wf, meta={"boot": 1})
            assert encode(msg, cache=mine) == encode_with_plan(msg)[0] == encode(msg)
    assert len(mine) == len(frames) and all(mine.holds(wf) for wf in frames)
    small = BodyCache(2)
    for wf in frames[:3]:
        small.body(wf, 50, None)
    assert len(small) == 2 and not small.holds(frames[0]) and small.holds(frames[2])
