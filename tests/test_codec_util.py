"""Shared helpers for the codec tests: message builders, a hypothesis strategy for valid
messages, an envelope sealer for crafting hostile payloads, and the round-trip checker.
(No tests here; the name only keeps it next to its users.)"""

from __future__ import annotations

import itertools
import math
import zlib
from typing import Any

import msgpack
import numpy as np
from hypothesis import strategies as st

import wire_codec
from mapping.se2 import Pose
from mapping.wireframe import Wireframe, as_masks
from wire_codec import reference
from wire_codec.codec import decode_with, encode_with_plan
from wire_codec.errors import DEFAULT_LIMITS, Limits

ROBOT, FUSED = wire_codec.MessageKind.ROBOT_MAP, wire_codec.MessageKind.FUSED_MAP
POSE = Pose(1.5, -2.25, 0.5)
ORIGIN = Pose()


def message(
    wf: Wireframe,
    *,
    kind: wire_codec.MessageKind = ROBOT,
    resolution: float = 0.2,
    robots: tuple[str, ...] = (),
    sender: str = "r1",
    seq: int = 7,
    stamp_ns: int = 1_700_000_000_000_000_000,
    pose: Pose = POSE,
    origin: Pose = ORIGIN,
    frame: str = "odom/r1",
    meta: dict[str, Any] | None = None,
) -> wire_codec.MapMessage:
    return wire_codec.MapMessage(
        kind=kind,
        sender=sender,
        seq=seq,
        stamp_ns=stamp_ns,
        pose=pose,
        frame=frame,
        origin=origin,
        resolution=resolution,
        wireframe=wf,
        robots=robots,
        meta={} if meta is None else meta,
    )


def room() -> Wireframe:
    """A 10 x 8 m L-shaped room (counterclockwise) with a 2 x 2 m obstacle (clockwise)."""
    outer = [(0, 0), (10, 0), (10, 6), (6, 6), (6, 8), (0, 8)]
    obstacle = [(2, 2), (2, 4), (4, 4), (4, 2)]
    return Wireframe.from_polylines([outer, obstacle])


def seal(fields: list[Any]) -> bytes:
    """Pack envelope ``fields`` (all but the CRC) exactly as the encoder does and append a
    valid CRC: lets a test craft a payload that is wrong only where it wants."""
    assert len(fields) < 15, "seal writes a fixarray header"
    packed = msgpack.packb(fields, use_bin_type=True)
    head = bytes([0x90 + len(fields) + 1]) + packed[1:]
    return head + b"\xce" + zlib.crc32(head).to_bytes(4, "big")


def fields_of(data: bytes) -> list[Any]:
    """The 12 envelope fields of a valid payload (without the CRC)."""
    obj = msgpack.unpackb(data, raw=False)
    return list(obj[:-1])


def random_wireframe(rng: np.random.Generator, n: int, style: str, density: str, resolution: float,
                     n_robots: int | None, label_style: str, lik_style: str) -> Wireframe:
    """A random valid wireframe. ``style``: rectilinear walk, random floats or far away;
    ``density``: rings, sparse random pairs, dense (all pairs of a few vertices, both ways)."""
    if style == "rect":
        steps = rng.integers(1, 40, size=n) * resolution * rng.choice([-1.0, 1.0], size=n)
        pts = np.zeros((n, 2))
        if n:
            pts[:, 0] = np.cumsum(np.where(np.arange(n) % 2 == 0, steps, 0.0))
            pts[:, 1] = np.cumsum(np.where(np.arange(n) % 2 == 1, steps, 0.0))
            pts += rng.normal(0.0, resolution / 10, size=(n, 2)) * (rng.random((n, 1)) < 0.2)
    elif style == "random":
        pts = rng.uniform(-50.0, 50.0, size=(n, 2))
    else:  # far away from the origin (but within the default limits)
        pts = rng.uniform(-5.0, 5.0, size=(n, 2)) + rng.choice([-1.0, 1.0], size=2) * rng.uniform(1e4, 2e6)
    if density == "rings" and n >= 2:
        cuts = np.sort(rng.choice(np.arange(1, n), size=min(int(rng.integers(0, 4)), n - 1), replace=False))
        edges = []
        for ring in np.split(np.arange(n), cuts):
            edges += [(int(a), int(b)) for a, b in itertools.pairwise(ring)]
            if len(ring) > 2 and rng.random() < 0.8:
                edges.append((int(ring[-1]), int(ring[0])))
        perm = rng.permutation(n)  # hide the chain order from the encoder
        pts = pts[np.argsort(perm)]
        edges = [(int(perm[a]), int(perm[b])) for a, b in edges]
        if edges and rng.random() < 0.3:  # a repeat and a reverse (thin wall)
            edges.append(edges[0])
            edges.append((edges[1][1], edges[1][0]) if len(edges) > 1 else (edges[0][1], edges[0][0]))
    elif density == "dense" and n >= 2:
        k = min(n, 7)
        edges = [(a, b) for a in range(k) for b in range(k) if a != b]
    elif n >= 2:
        m = int(rng.integers(0, 3 * n))
        a = rng.integers(0, n, size=m)
        b = (a + rng.integers(1, n, size=m)) % n
        edges = list(zip(a.tolist(), b.tolist()))
    else:
        edges = []
    m = len(edges)
    if label_style == "constant":
        labels = np.full(n, int(rng.integers(0, 3)), dtype=np.uint8)
    elif label_style == "mostly":
        labels = np.where(rng.random(n) < 0.85, 0, rng.integers(1, 3, size=n)).astype(np.uint8)
    else:
        labels = rng.integers(0, 3, size=n).astype(np.uint8)
    if lik_style == "constant":
        lik = np.full(m, rng.choice([0.0, 0.5, 1.0, float(rng.random())]))
    elif lik_style == "mostly":
        lik = np.where(rng.random(m) < 0.85, 1.0, rng.random(m))
    else:
        lik = rng.random(m)
        if m:
            lik[rng.random(m) < 0.2] = 0.0
    if n_robots and n_robots > 64:  # masks past bit 63: Python ints (mapping.wireframe.as_masks)
        wide = [int.from_bytes(rng.bytes((n_robots + 7) // 8), "big") >> (-n_robots % 8) for _ in range(m)]
        if m:
            wide[0] = (1 << n_robots) - 1  # every robot, the top bit included
        if m > 1:
            wide[-1] = 1 << (n_robots - 1)  # the last robot alone
        src = as_masks(wide) if m else np.zeros(0, dtype=np.uint64)
    elif n_robots:
        top = (1 << n_robots) - 1 if n_robots < 64 else (1 << 64) - 1
        src = np.array([int(rng.integers(0, 1 << min(n_robots, 62))) & top for _ in range(m)],
                       dtype=np.uint64)
        if m and n_robots == 64:
            src[0] = np.uint64((1 << 64) - 1)
    else:
        src = np.zeros(m, dtype=np.uint64)
    return Wireframe.build(pts.reshape(-1, 2), np.array(edges, dtype=np.int64).reshape(-1, 2),
                           labels, lik, src)


@st.composite
def messages(
    draw: st.DrawFn, max_vertices: int = 40, robot_counts: tuple[int, ...] = (0, 1, 3, 8, 64)
) -> wire_codec.MapMessage:
    """Random valid messages: every kind, shape and size the format has to carry (fused maps
    of ``robot_counts`` robots; with only counts over 64, fused maps only: format version 2)."""
    fused = True if min(robot_counts) > 64 else draw(st.booleans())
    n = draw(st.one_of(st.sampled_from([0, 1, 2, 3]), st.integers(0, max_vertices)))
    style = draw(st.sampled_from(["rect", "rect", "random", "far"]))
    density = draw(st.sampled_from(["rings", "rings", "sparse", "dense"]))
    resolution = draw(st.sampled_from([0.2, 0.4, 0.05, 1.0, 0.001, 0.1234]))
    n_robots = draw(st.sampled_from(list(robot_counts))) if fused else None
    label_style = draw(st.sampled_from(["constant", "mostly", "random"]))
    lik_style = draw(st.sampled_from(["constant", "mostly", "random"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    wf = random_wireframe(rng, n, style, density, resolution, n_robots, label_style, lik_style)
    theta = draw(st.floats(-math.pi, math.pi, allow_nan=False))
    pose = Pose(draw(st.floats(-1e4, 1e4)), draw(st.floats(-1e4, 1e4)), theta)
    meta = draw(st.sampled_from([{}, {"stale": ["r2"]},
                                 {"note": "x" * 40, "k": 1.5, "b": b"\x00\x01", "n": None}]))
    if fused:
        robots = tuple(f"robot{k}" for k in range(n_robots or 0))
        return message(wf, kind=FUSED, resolution=resolution, robots=robots, sender="fusion",
                       pose=Pose(), frame="fleet", seq=draw(st.integers(0, 2**64 - 1)), meta=meta)
    return message(wf, resolution=resolution, pose=pose, origin=Pose(3.0, -4.0, 1.0),
                   stamp_ns=draw(st.integers(0, 2**64 - 1)),
                   sender=draw(st.sampled_from(["r1", "röbot-ß", "r" * 64])), meta=meta)


def check_round_trip(msg: wire_codec.MapMessage, limits: Limits = DEFAULT_LIMITS) -> bytes:
    """Encode, decode (fast and reference) and check every promise of the format."""
    data, plan = encode_with_plan(msg)
    out = wire_codec.decode(data, limits=limits)
    ref = decode_with(data, limits, reference.decode_body)
    wf, got = msg.wireframe, out.wireframe
    n, m = wf.n_vertices, wf.n_edges
    assert (got.n_vertices, got.n_edges) == (n, m)
    order, eorder = plan.vertex_order, plan.edge_order
    assert sorted(order.tolist()) == list(range(n)) and sorted(eorder.tolist()) == list(range(m))
    res = round(msg.resolution * 1e3) / 1e3
    assert out.resolution == res
    if n:
        src_pts = wf.points[order]
        err = np.abs(got.points - src_pts)
        assert np.all(err <= res / 2 + 1e-9 * np.maximum(1.0, np.abs(src_pts))), float(err.max())
        # Snapped to the grid: re-quantising gives the same point (no drift on re-encoding).
        q = np.rint(got.points / res)
        assert np.array_equal(q * round(res * 1e3) / 1e3, got.points)
    assert np.array_equal(got.labels, wf.labels[order])
    inv = np.empty(n, dtype=np.int64)
    inv[order] = np.arange(n)
    assert np.array_equal(got.edges, inv[wf.edges[eorder]].reshape(-1, 2))
    assert np.all(np.abs(got.likelihood - wf.likelihood[eorder]) <= 1 / 30 + 1e-12)
    assert np.array_equal(got.likelihood, np.rint(wf.likelihood[eorder] * 15) / 15)
    assert np.array_equal(got.sources, wf.sources[eorder])
    assert ((out.kind, out.sender, out.seq, out.stamp_ns, out.frame)
            == (msg.kind, msg.sender, msg.seq, msg.stamp_ns, msg.frame))
    assert out.robots == tuple(msg.robots) and out.meta == msg.meta
    for a, b in ((out.pose, msg.pose), (out.origin, msg.origin)):
        assert a.almost_equal(b, tol=0.0005 + 1e-9, angle_tol=5e-7 + 1e-12)
    # The literal reference decoder reads exactly the same map.
    rw = ref.wireframe
    assert np.array_equal(rw.points, got.points) and np.array_equal(rw.edges, got.edges)
    assert np.array_equal(rw.labels, got.labels) and np.array_equal(rw.likelihood, got.likelihood)
    assert np.array_equal(rw.sources, got.sources)
    return data
