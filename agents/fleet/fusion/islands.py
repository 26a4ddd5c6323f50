"""The fusion service's side of robots of unknown start pose (see :mod:`.frames`).

:class:`IslandShell` runs the registration attempts of :class:`FusionState` (one at a time,
when no map waits, at most every ``register_wait_s``), and publishes each island -- robots of
unknown origin not registered into the fleet frame -- on
``wiremap/<fleet>/fused/islands/<root>`` as a ``FUSED_MAP`` in its root robot's frame
(``frame = "odom/<root>"``, ``robots`` its members, ``meta = {island: true, root, version}``);
an island that joined the fleet gets a DELETE on its key. Registrations go to the service's log,
to the recording (:meth:`FleetRecorder.log_registration`) and, with their scores, to
``fused/stats`` and the fused map's ``meta["frames"]`` (which ``wiremap watch`` shows).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from agents.fleet.fusion.codec import encode_message
from agents.fleet.fusion.frames import RegistrationRecord
from agents.fleet.fusion.state import FusionState
from mapping.se2 import Pose
from wire_codec.message import MapMessage, MessageKind

#: Registration records kept in ``fused/stats`` and in the fused map's meta.
RECENT = 8


def islands_key(keys: Any, root: str | None = None) -> str:
    """``wiremap/<fleet>/fused/islands/<root>`` (``*`` for every island)."""
    return f"{keys.prefix}/fused/islands/{root if root is not None else '*'}"


def island_message(
    st: FusionState, root: str, members: tuple[str, ...], wf: Any, stamp_ns: int
) -> MapMessage:
    """An island as a ``FUSED_MAP`` in its root robot's frame."""
    return MapMessage(
        kind=MessageKind.FUSED_MAP, sender=st.sender, seq=st.version, stamp_ns=int(stamp_ns),
        pose=Pose.identity(), frame=f"odom/{root}", origin=Pose.identity(), resolution=st.resolution,
        wireframe=wf, robots=members,
        meta={
            "island": True, "root": root, "version": st.version, "threshold": st.threshold,
            "registrations": [r.as_dict() for r in st.frames.records if root in (r.a, r.b)][-3:],
        },
    )


def frames_section(st: FusionState) -> dict[str, Any]:
    """``fused/stats``'s ``frames``: the graph's summary and the last registrations."""
    doc = st.frames.summary()
    doc["registrations"] = [r.as_dict() for r in st.frames.records[-RECENT:]]
    doc["island_maps"] = {
        root: {"robots": list(ms), "vertices": wf.n_vertices, "edges": wf.n_edges}
        for root, (ms, wf) in st.islands().items()
    }
    return doc


class IslandShell:
    """Registration attempts and island publication for :class:`FusionService`."""

    def __init__(
        self, session: Any, keys: Any, recorder: Any, say: Callable[[str], None], register_wait_s: float = 0.5
    ) -> None:
        self.session = session
        self.keys = keys
        self.recorder = recorder
        self.say = say
        self.register_wait_s = register_wait_s
        self.last = -1e9
        self.published: dict[str, tuple[tuple[str, ...], Any]] = {}  # root -> (members, map id) last put
        self.seconds = 0.0
        self.last_pub = -1e9

    def step(self, st: FusionState, now: float, idle: bool) -> bool:
        """One registration attempt when the state has a due pair, ``idle`` (no map waits) and
        ``register_wait_s`` passed. Returns whether the fleet frame changed (fuse again)."""
        if not st.frames.active or not idle or now - self.last < self.register_wait_s:
            return False
        self.last = now
        t0 = time.perf_counter()
        rec = st.register_step(t=st.registration_clock(), now=now)
        self.seconds += time.perf_counter() - t0
        if rec is None:
            return False
        self.note(st, rec)
        return rec.accepted

    def note(self, st: FusionState, rec: RegistrationRecord) -> None:
        self.say(rec.line())
        if self.recorder is not None:
            self.recorder.log_registration(rec.t, rec.line(), rec.a, rec.b, rec.accepted, rec.confidence,
                                           rec.support)

    def publish(self, st: FusionState, stamp_ns: int) -> None:
        """Put every island whose map changed; DELETE the key of an island that is gone."""
        if not st.frames.active:
            return
        self.last_pub = time.monotonic()
        isl = st.islands()
        for root, (members, wf) in isl.items():
            ident = (members, st.island_key(root))
            if self.published.get(root) == ident:
                continue
            self.published[root] = ident
            data = encode_message(island_message(st, root, members, wf, stamp_ns))
            self.session.put(islands_key(self.keys, root), data)
            if self.recorder is not None:
                self.recorder.log_island(st.sim_time(), root, members, wf)
        for root in [r for r in self.published if r not in isl]:
            del self.published[root]
            try:
                self.session.delete(islands_key(self.keys, root))
            except Exception:  # pragma: no cover - session closing
                pass
            if self.recorder is not None:
                self.recorder.log_island(st.sim_time(), root, (), None)
