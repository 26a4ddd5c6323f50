"""Fused-map fingerprint: a hash of the fused map's bytes (one process, fast and full path; a
tree of 2 regional states and a root) for 3, 16 and 64 synthetic museum robots
(:func:`tests.tree_util.robot_views`, seed 0). Two checkouts print the same lines exactly when
they fuse those fleets byte for byte alike (how the widening of the masks was checked, issue 21).

    python -m tests.fused_fingerprint > A     # in each checkout, then: diff A B
"""

from __future__ import annotations

import hashlib

from agents.fleet.fusion import FusionConfig, FusionState, encode_message
from tests.tree_util import robot_views, tree_fuse

THR = 0.4


def main() -> None:
    out = {}
    for n in (3, 16, 64):
        _fleet(n, out)
    for k, v in out.items():
        print(k, v)


def _fleet(n: int, out: dict[str, str]) -> None:
    msgs = robot_views("museum", n, seed=0)
    raws = {m.sender: encode_message(m) for m in msgs}
    st = FusionState(FusionConfig(threshold=THR))
    for rid, raw in raws.items():
        st.offer(raw, rid)
    st.fuse(full=False)
    fast = encode_message(st.fused_message(0))
    st.fuse(full=True)
    full = encode_message(st.fused_message(0))
    ids = sorted(raws)
    half = len(ids) // 2 if n > 3 else 2
    root, _ = tree_fuse(raws, [ids[:half], ids[half:]], THR)
    tree = encode_message(root.fused_message(0))
    for name, b in (("fast", fast), ("full", full), ("tree", tree)):
        out[f"{n}-{name}"] = hashlib.sha256(b).hexdigest()[:16] + f" {len(b)}B"


if __name__ == "__main__":
    main()
