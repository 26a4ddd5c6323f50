"""Robot maps for the fusion-tree tests: views of a world's true walls as robots would send them
(a window of the walls around each robot, a little noise, in the robot's odometry frame), and the
tree's merge of them in one process."""

from __future__ import annotations

import numpy as np

from agents.fleet.fusion import FusionConfig, FusionState, decode_message, encode_message
from agents.fleet.fusion.tree import RootState
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe
from wire_codec.message import MapMessage, MessageKind


def robot_views(world: str, n: int, seed: int = 0, radius: float = 25.0, noise: float = 0.03,
                start_error: float = 0.1) -> list[MapMessage]:
    """``n`` robot maps (ids ``r01``..) of ``world``: each the true walls whose both ends lie
    within ``radius`` of a random point, vertex noise ``noise`` m, expressed in an odometry frame
    whose origin (the start pose sent) is off by up to ``start_error`` m / 1 degree."""
    from agents.sim.world import load_world

    truth = load_world(world).truth
    rng = np.random.default_rng(seed)
    lo, hi = truth.points.min(axis=0), truth.points.max(axis=0)
    out = []
    for k in range(n):
        rid = f"r{k + 1:02d}"
        c = lo + rng.random(2) * (hi - lo)
        near = np.linalg.norm(truth.points - c, axis=1) <= radius
        keep = near[truth.edges[:, 0]] & near[truth.edges[:, 1]]
        if not keep.any():
            keep[np.argmin(np.linalg.norm(truth.points[truth.edges[:, 0]] - c, axis=1))] = True
        edges = truth.edges[keep]
        used = np.unique(edges)
        remap = -np.ones(truth.n_vertices, dtype=np.int64)
        remap[used] = np.arange(len(used))
        pts = truth.points[used] + rng.normal(0.0, noise, (len(used), 2))
        labels = truth.labels[used].copy()
        deg = np.bincount(remap[edges].ravel(), minlength=len(used))
        labels[deg == 1] = Label.FRONTIER
        wf = Wireframe(pts, labels, remap[edges], np.full(len(edges), 0.6),
                       np.zeros(len(edges), dtype=np.uint64))
        origin = Pose(float(c[0]), float(c[1]), float(rng.uniform(-np.pi, np.pi)))
        err = Pose(*rng.uniform(-start_error, start_error, 2), float(np.radians(rng.uniform(-1, 1))))
        sent = origin.compose(err)
        out.append(MapMessage(
            kind=MessageKind.ROBOT_MAP, sender=rid, seq=1, stamp_ns=1_000 + k, pose=Pose.identity(),
            frame=f"odom/{rid}", origin=sent, resolution=0.05, wireframe=wf.transformed(origin.inverse()),
            meta={"boot": 1, "t": 1.0},
        ))
    return out


def tree_fuse(raws: dict[str, bytes], groups: list[list[str]], threshold: float,
              refine: bool = True) -> tuple[RootState, MapMessage]:
    """The fusion tree in one process: each group a regional FusionState (full path, aligned
    onto the partials before it), its partial through the codec, the root's merge through the
    codec. Returns the root and its fused map as a subscriber decodes it."""
    root = RootState(threshold)
    for g, ids in enumerate(groups):
        st = FusionState(FusionConfig(threshold=threshold, refine=refine, close_frontiers=False),
                         sender=f"g{g}")
        for r in ids:
            st.offer(raws[r], r)
        st.base = root.prefix_before(ids)
        st.fuse(full=True)
        root.offer(f"g{g}", decode_message(encode_message(st.fused_message(0, {"boot": 1}))))
    root.fuse()
    return root, decode_message(encode_message(root.fused_message(0)))
