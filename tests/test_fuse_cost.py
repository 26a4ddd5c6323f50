"""The cheaper fuse of issue 21 gives the same maps as before, bit for bit: the fold's nodes
snapped to the wire's grid (:func:`wire_snap`) and its leaves (:meth:`FusionState._ready`) are
built with :meth:`Wireframe.checked` instead of the checking constructor, the same arrays."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import wire_codec
from agents.fleet.fusion import FusionConfig, FusionState, encode_message
from agents.fleet.fusion.tree import wire_snap
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from tests.test_codec_util import messages
from tests.tree_util import robot_views

NAMES = ("points", "labels", "edges", "likelihood", "sources")


def same_arrays(a: Wireframe, b: Wireframe) -> None:
    for name in NAMES:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name
        assert not x.flags.writeable and x.flags.c_contiguous


@settings(max_examples=200, deadline=2000)
@given(messages(), st.sampled_from([0.001, 0.01, 0.05, 0.137, 0.4]))
def test_wire_snap_is_the_checking_constructors(msg: wire_codec.MapMessage, res: float) -> None:
    wf = wire_codec.decode(wire_codec.encode(msg)).wireframe.transformed(Pose(0.0123, -0.0456, 0.3))
    out = wire_snap(wf, res)
    res_mm = max(1, round(res * 1e3))
    ref = Wireframe(np.rint(wf.points / (res_mm / 1e3)) * res_mm / 1e3, wf.labels, wf.edges,
                    np.rint(wf.likelihood * 15) / 15, wf.sources)
    same_arrays(out, ref)


def test_leaves_are_the_checking_constructors() -> None:
    st_ = FusionState(FusionConfig(threshold=0.4))
    for m in robot_views("museum", 6, seed=4):
        st_.offer(encode_message(m), m.sender)
    st_.fuse()
    for k, rid in enumerate(st_.fused_robots):
        corr = st_.corrections.get(rid)
        got = st_._ready(rid, corr, k)
        m = st_.robots[rid].message
        pose = m.origin if corr is None else corr.compose(m.origin)
        src = m.wireframe
        ref = wire_snap(Wireframe(pose.apply(src.points), src.labels, src.edges, src.likelihood,
                                  np.full(src.n_edges, 1 << k, np.uint64)), st_.resolution)
        same_arrays(got, ref)
