"""The cheaper intake of issue 21 gives the same answers as before, bit for bit.

* :func:`too_dense` (shortcuts for small maps, a dense ``bincount`` instead of ``np.unique``)
  against the former implementation, kept here as the reference, on honest maps, hostile
  stacks and random maps (also spans over ``DENSE_CELLS``, the ``np.unique`` fallback);
* :meth:`Wireframe.checked` (the decoder's constructor without value checks) against the
  checking constructor on decoded maps of every shape; its dtype and shape checks;
* :meth:`Wireframe.transformed` (only the moved points checked) against the checking
  constructor;
* :meth:`FleetSamples.view` (each robot's view of the other robots' walls, cut from samples
  taken once per fused version) against :meth:`FleetView.of` over :func:`others_walls`.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import wire_codec
from agents.fleet.fusion import FusionConfig, FusionState, encode_message
from agents.fleet.fusion.intake import DENSITY_STEP_M, InputLimits, over_budget, too_dense
from agents.fleet.fusion.quarantine import FleetSamples, FleetView, QuarantineConfig, others_walls
from agents.sim.world import load_world
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from tests.test_codec_util import message, messages
from tests.tree_util import robot_views
from wire_codec.body import _decode_small


def too_dense_reference(wf: Wireframe, limits: InputLimits) -> tuple[str, str] | None:
    """``too_dense`` as it was before issue 21 (np.unique over cell codes, no shortcuts)."""

    def codes(xy: np.ndarray) -> np.ndarray:
        c = np.floor(xy).astype(np.int64)
        return (c[:, 0] << 32) + c[:, 1]

    if wf.n_vertices == 0:
        return None
    _, per_cell = np.unique(codes(wf.points), return_counts=True)
    if int(per_cell.max()) > limits.max_cell_vertices:
        return ("budget_density",
                f"{int(per_cell.max())} vertices in one square metre (budget {limits.max_cell_vertices})")
    if wf.n_edges == 0:
        return None
    seg = wf.points[wf.edges]
    length = np.hypot(*(seg[:, 1] - seg[:, 0]).T)
    k = np.maximum(1, np.ceil(length / DENSITY_STEP_M).astype(np.int64))
    owner = np.repeat(np.arange(len(seg)), k)
    t = (np.arange(int(k.sum())) - np.repeat(np.cumsum(k) - k, k) + 0.5) / k[owner]
    pts = seg[owner, 0] + t[:, None] * (seg[owner, 1] - seg[owner, 0])
    cells, inv = np.unique(codes(pts), return_inverse=True)
    metres = np.bincount(inv, weights=(length / k)[owner], minlength=len(cells))
    most = float(metres.max())
    if most > limits.max_cell_wall_m:
        return ("budget_density",
                f"{most:.0f} m of walls in one square metre (budget {limits.max_cell_wall_m:g} m)")
    return None


def same_verdicts(wf: Wireframe, limits: InputLimits) -> tuple[str, str] | None:
    ref = too_dense_reference(wf, limits)
    assert too_dense(wf, limits) == ref
    if wf.n_edges:
        seg = wf.points[wf.edges]
        assert too_dense(wf, limits, np.hypot(*(seg[:, 1] - seg[:, 0]).T)) == ref
    return ref


TIGHT = InputLimits(max_cell_vertices=3, max_cell_wall_m=3.0)  # so honest maps hit both checks


@pytest.mark.parametrize("limits", [InputLimits(), TIGHT])
def test_honest_maps_same_verdicts(limits: InputLimits) -> None:
    truth = load_world("museum").truth
    same_verdicts(truth, limits)
    for m in robot_views("museum", 16, seed=0):
        same_verdicts(m.wireframe, limits)


def test_hostile_stacks_same_verdicts() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.0, 1.0, size=(200, 2))
    chain = Wireframe.build(pts, np.stack([np.arange(199), np.arange(1, 200)], axis=1))
    assert same_verdicts(chain, InputLimits()) is not None
    star = Wireframe.build(
        np.array([[0.5, 0.5]] + [[0.5 + 3 * np.cos(a), 0.5 + 3 * np.sin(a)] for a in np.linspace(0, 6, 40)]),
        np.array([[0, k] for k in range(1, 41)]),
    )
    assert same_verdicts(star, InputLimits(max_cell_vertices=100)) is not None
    # seven 3 m walls through one cell: over 12 m there, just past the shortcut's 6 edges
    fan = Wireframe.build(
        np.array([[0.5 + 1.5 * np.cos(a) * s, 0.5 + 1.5 * np.sin(a) * s]
                  for a in np.linspace(0, 3, 7) for s in (-1, 1)]),
        np.arange(14).reshape(7, 2),
    )
    assert same_verdicts(fan, InputLimits(max_cell_wall_m=6.0)) is not None
    # a stack spread over a box wider than DENSE_CELLS (the np.unique fallback)
    far = np.concatenate([pts, [[900.0, -900.0], [-900.0, 900.0]]])
    wide = Wireframe.build(far, np.stack([np.arange(201), np.arange(1, 202)], axis=1))
    assert same_verdicts(wide, InputLimits()) is not None


@settings(max_examples=300, deadline=2000)
@given(
    n=st.integers(1, 60),
    box=st.sampled_from([0.7, 2.0, 5.0, 30.0, 400.0]),
    edges=st.integers(0, 80),
    seed=st.integers(0, 2**32 - 1),
    cell_v=st.integers(1, 40),
    cell_m=st.sampled_from([0.5, 2.0, 3.9, 4.0, 6.0, 12.0, 12.1]),
)
def test_random_maps_same_verdicts(n: int, box: float, edges: int, seed: int, cell_v: int,
                                   cell_m: float) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-box, box, size=(n, 2)).round(2)
    e = rng.integers(0, n, size=(edges, 2)) if n > 1 else np.zeros((0, 2), np.int64)
    e = e[e[:, 0] != e[:, 1]]
    same_verdicts(Wireframe.build(pts, e), InputLimits(max_cell_vertices=cell_v, max_cell_wall_m=cell_m))


def test_over_budget_passes_its_lengths_without_changing_a_verdict() -> None:
    truth = load_world("museum").truth
    msg = message(truth, resolution=0.05, origin=Pose())
    assert over_budget(msg, InputLimits(max_robot_wall_m=1e5)) is None  # the whole museum: 5 km
    tight = InputLimits(max_robot_wall_m=1e5, max_cell_wall_m=1.0)
    assert over_budget(msg, tight) == too_dense_reference(truth, tight) is not None


# ---------------------------------------------------------------------- Wireframe.checked
@settings(max_examples=300, deadline=2000)
@given(messages())
def test_the_decoders_wireframe_is_the_checking_constructors(msg: wire_codec.MapMessage) -> None:
    data = wire_codec.encode(msg)
    out = wire_codec.decode(data).wireframe
    again = Wireframe(out.points, out.labels, out.edges, out.likelihood, out.sources)  # every check
    for name in ("points", "labels", "edges", "likelihood", "sources"):
        a, b = getattr(out, name), getattr(again, name)
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name
        assert not a.flags.writeable and a.flags.c_contiguous
    assert out.content_digest() == again.content_digest()


@settings(max_examples=200, deadline=2000)
@given(messages(), st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), st.floats(-7.0, 7.0))
def test_transformed_is_the_checking_constructors(msg: wire_codec.MapMessage, x: float, y: float,
                                                  theta: float) -> None:
    wf = wire_codec.decode(wire_codec.encode(msg)).wireframe
    pose = Pose(x, y, theta)
    out = wf.transformed(pose)
    ref = Wireframe(pose.apply(wf.points), wf.labels, wf.edges, wf.likelihood, wf.sources)  # every check
    for name in ("points", "labels", "edges", "likelihood", "sources"):
        a, b = getattr(out, name), getattr(ref, name)
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name
        assert not a.flags.writeable and a.flags.c_contiguous
    wide = wf.replace(sources=np.array([int(s) << 64 for s in wf.sources.tolist()], dtype=object))
    assert wide.transformed(pose).sources.tolist() == wide.sources.tolist()


def test_transformed_still_refuses_points_it_cannot_hold() -> None:
    wf = Wireframe.build(np.array([[1e308, 0.0], [0.0, 1.0]]), np.array([[0, 1]]))
    with np.errstate(over="ignore"), pytest.raises(ValueError, match="non-finite"):
        wf.transformed(Pose(1e308, 0.0, 0.0))


def test_small_reader_uses_checked() -> None:
    msg = message(Wireframe.from_polylines([[(0, 0), (4, 0), (4, 3), (0, 3)]]))
    fields = wire_codec.decode(wire_codec.encode(msg))
    assert fields.wireframe.n_edges == 4
    body = wire_codec.encode(msg)
    import msgpack

    raw_body = msgpack.unpackb(body, raw=False)[11]
    wf = _decode_small(raw_body, 200, None, wire_codec.Limits())
    assert wf is not None and not wf.points.flags.writeable


def test_checked_refuses_arrays_of_the_wrong_kind() -> None:
    pts = np.zeros((3, 2))
    lab = np.zeros(3, np.uint8)
    e = np.array([[0, 1], [1, 2]], np.int32)
    lik = np.ones(2)
    src = np.zeros(2, np.uint64)
    assert Wireframe.checked(pts.copy(), lab.copy(), e.copy(), lik.copy(), src.copy()).n_edges == 2
    bad = [
        (pts.astype(np.float32), lab, e, lik, src),
        (pts, lab.astype(np.int64), e, lik, src),
        (pts, lab, e.astype(np.int64), lik, src),
        (pts, lab, e, lik[:1], src),
        (pts, lab, e, lik, src.astype(np.int64)),
        (pts[:, :1], lab, e, lik, src),
        (np.asfortranarray(np.zeros((3, 2))), lab, e, lik, src),
        (pts.tolist(), lab, e, lik, src),
    ]
    for args in bad:
        with pytest.raises(ValueError, match=r"Wireframe\.checked"):
            Wireframe.checked(*args)  # type: ignore[arg-type]


# ---------------------------------------------------------------------- FleetSamples.view
def same_view(a: FleetView, b: FleetView) -> None:
    assert np.array_equal(a.cells, b.cells) and a.cells.dtype == b.cells.dtype
    assert (a.near is None) == (b.near is None)
    if a.near is not None and b.near is not None:
        assert a.near.data.tobytes() == b.near.data.tobytes()


@pytest.mark.parametrize("n", [3, 16])
def test_each_robots_fleet_view_is_cut_exactly(n: int) -> None:
    st = FusionState(FusionConfig(threshold=0.4, refine=False))
    for m in robot_views("museum", n, seed=0):
        st.offer(encode_message(m), m.sender)
    st.fuse()
    fused = st.fused
    assert fused.n_edges and len(np.unique(fused.sources)) > 2
    for cfg in (QuarantineConfig(), QuarantineConfig(sample_m=0.7, cell_m=3.0)):
        samples = FleetSamples.of(fused, cfg)
        for bit in [None, *range(n), n + 3, 70]:
            same_view(samples.view(bit), FleetView.of(others_walls(fused, bit), cfg))
    wide = fused.replace(sources=np.array([int(s) << 60 for s in fused.sources.tolist()], dtype=object))
    samples = FleetSamples.of(wide, QuarantineConfig())
    for bit in [None, 60, 61, 64, 66]:
        same_view(samples.view(bit), FleetView.of(others_walls(wide, bit), QuarantineConfig()))
    empty = FleetSamples.of(Wireframe.empty(), QuarantineConfig()).view(2)
    assert empty.near is None and len(empty.cells) == 0
